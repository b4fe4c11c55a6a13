"""Trace a floor grid on a Dask cluster: tiles out, arrays back, one grid file.

:func:`trace_grid_tiled` is :func:`isac_twin.raytrace.grid.trace_grid` (chain
reuse) with the free points split into tiles (:mod:`isac_twin.scaleout.tiles`)
that the workers of a ``distributed.Client`` trace; the client assembles the
same :class:`~isac_twin.raytrace.grid.PathGrid` (arrays and metadata) that the
single-process trace gives. :func:`cluster_client` starts a local cluster of
``N`` spawned single-threaded worker processes or connects to a scheduler.

Nothing is lost:

- a tile whose worker dies (killed, out of memory) is re-run on another worker
  by the scheduler (``distributed.scheduler.allowed-failures``, default 3
  deaths per task, then ``KilledWorker``); a local cluster's nanny restarts
  the dead worker process;
- every finished tile is written to a checkpoint folder
  (:mod:`isac_twin.scaleout.checkpoint`), so a build that was interrupted
  (Ctrl-C, the client machine rebooted) resumes with the missing tiles only;
- a tqdm progress bar counts finished tiles.

Each AP's chains are enumerated once, by one worker, and sent to every
worker (:mod:`isac_twin.scaleout.shared_chains`). The ``verify`` re-trace runs on
the workers too, point by point (:func:`~isac_twin.raytrace.grid.verify_point`:
the points ``trace_grid`` picks, the same counts in ``meta["verification"]``),
each point's task submitted as soon as its tile is back.

What differs from ``trace_grid``: ``meta["scaleout"]`` says how the grid was
built (tiles, tile size, workers, tiles resumed from checkpoints) and where
the time went (``seconds``: planning, tracing, verification, assembly in the
client; ``chains``: per AP the worker that enumerated it and how long it took;
``worker_runs``: per worker process its tiles, scene load, tracing and idle
time at the end; ``verify_s``: per verified point).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np

from ..raytrace.chains import CHAIN_REUSE_VERSION
from ..raytrace.grid import (
    CHAIN_CHUNK_SIZE,
    GRID_SPEC_TABLE_SIZE,
    VERIFY_TOP_N,
    PathGrid,
    assemble_grid,
    grid_metadata,
    save_grid,
    verification_summary,
    verify_pick,
)
from ..scene.config import TracerConfig
from .checkpoint import TileCheckpoints, checkpoint_key
from .tiles import (
    DEFAULT_WORKER_THREADS,
    GridPlan,
    TileJob,
    plan_grid,
    point_paths,
    scene_folder,
    shoot_source,
    trace_tile,
    verify_points,
)

log = logging.getLogger(__name__)

#: The worker preload module (:mod:`isac_twin.scaleout.preload`): local workers
#: import the tracer stack when they start, not in their first tile.
PRELOAD = "isac_twin.scaleout.preload"


def check_cluster_args(workers: int | None, scheduler: str | None) -> None:
    """Refuse ``workers`` together with ``scheduler``, and ``workers < 1``.

    Raises:
        ValueError: one line saying which.
    """
    if workers is not None and scheduler is not None:
        raise ValueError("--workers and --scheduler: give one of them (a local cluster of "
                         "N workers, or the address of a running scheduler), not both")
    if workers is not None and int(workers) < 1:
        raise ValueError(f"--workers {workers}: expected at least 1 worker process")
    if scheduler is not None and not str(scheduler).strip():
        raise ValueError("--scheduler: expected an address such as tcp://host:8786")


def _check_spawn() -> None:
    import dask

    method = dask.config.get("distributed.worker.multiprocessing-method", "spawn")
    if method == "fork":
        raise ValueError("dask config distributed.worker.multiprocessing-method is 'fork': "
                         "Dr.Jit must not be forked after it initialised; set it to 'spawn'")


@contextlib.contextmanager
def cluster_client(workers: int | None = None, scheduler: str | None = None, *,
                   memory_limit: str | float = "auto") -> Iterator:
    """A ``distributed.Client``: a local cluster of ``workers`` spawned
    single-threaded worker processes (closed on exit), or connected to the
    scheduler at ``scheduler`` (left running).

    Args:
        workers: worker processes of a local cluster (one thread each).
        scheduler: address of a running scheduler (``tcp://host:8786``).
        memory_limit: per local worker (Dask's ``memory_limit``; a worker that
            exceeds 95 % of it is restarted and its tile re-run).

    Local workers start with the :data:`PRELOAD` module (Sionna RT imported
    at start-up), without Dask's statistical profiler, and the scheduler hands
    a worker its next tile only when it finished one
    (``distributed.scheduler.worker-saturation`` 1).

    Raises:
        ValueError: both or neither given, ``workers < 1``, or a fork start method.
    """
    from distributed import Client, LocalCluster

    check_cluster_args(workers, scheduler)
    if workers is None and scheduler is None:
        raise ValueError("cluster_client: give workers or scheduler")
    if scheduler is not None:
        with Client(scheduler) as client:
            yield client
        return
    import dask

    _check_spawn()
    # worker-saturation 1: a worker gets its next tile when it finished one (no
    # tile waits in a busy worker's queue while another worker is idle at the end);
    # no statistical profiler sampling the workers' stacks every 10 ms (~1.5 % of a
    # worker's CPU, measured; with every core tracing it is time taken from a tile)
    with dask.config.set({"distributed.scheduler.worker-saturation": 1.0,
                          "distributed.worker.profile.enabled": False}), \
            LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True,
                         dashboard_address=":0", memory_limit=memory_limit,
                         silence_logs=logging.ERROR, preload=[PRELOAD]) as cluster, \
            Client(cluster) as client:
        yield client


def trace_grid_tiled(scene, tx_names: Sequence[str] | None = None, spacing: float = 0.05,
                     height: float | None = None, margin: float = 0.0, *, client,
                     config: TracerConfig | None = None, tile_size: int | None = None,
                     checkpoints: str | Path | None = None, progress: bool = True,
                     keep_strongest: int | None = None,
                     method: str | None = None, deterministic: bool | None = None,
                     max_cap: int | None = None, chunk_size: int | None = None,
                     worker_threads: int = DEFAULT_WORKER_THREADS, verify: int = 0,
                     verify_top: int = VERIFY_TOP_N, out: str | Path | None = None,
                     on_tile: Callable[[dict], None] | None = None) -> PathGrid:
    """Trace a floor grid on the workers of ``client`` (see the module doc).

    Args:
        scene: the :class:`~isac_twin.scene.twin_scene.TwinScene`; workers load its folder
            (same path on every worker) and must get the same content hash.
        tx_names, spacing (m), height (m), margin (m), config, keep_strongest,
            method, deterministic, chunk_size: as
            :func:`~isac_twin.raytrace.grid.trace_grid` (``method`` must be chain reuse).
        max_cap: accepted for ``trace_grid``'s signature; chain reuse has no
            candidate buffer, so there is no cap to grow.
        client: a ``distributed.Client`` (see :func:`cluster_client`).
        tile_size: free points per tile (a task), a multiple of ``chunk_size``
            (default: one chunk, 1024 points): a point's paths may depend on
            which points share its image-method calls (measured in the lab:
            3-6 of 6,144 links differ by a path when 3,072 points are traced
            in calls of other points), so tiles keep ``trace_grid``'s chunks,
            and the last full chunk is split between tiles only at
            image-method call boundaries (:data:`~isac_twin.scaleout.tiles.TAIL_PARTS`).
        checkpoints: the checkpoint folder (None: no checkpoints); finished
            tiles are kept there until the grid is complete.
        progress: tqdm progress bar over tiles.
        worker_threads: Dr.Jit threads per worker process.
        verify, verify_top: as ``trace_grid``'s (the same points re-traced
            directly and compared, :func:`~isac_twin.raytrace.grid.verify_point`,
            on the workers: a point's task is submitted when its tile is
            back); default 0 (none).
        out: also write the grid NPZ there.
        on_tile: called in the client with each finished tile's summary
            (``index``, ``pid``, ``chains``, ``setup_s``, ``trace_s``, ``start``,
            ``end``: see :func:`~isac_twin.scaleout.tiles.trace_tile`) as it arrives.

    Returns:
        The :class:`~isac_twin.raytrace.grid.PathGrid`.

    Raises:
        ValueError: bad arguments, an ``sbr`` method, or a worker whose scene
            folder differs.
        distributed.KilledWorker: a tile killed its workers too often.
    """
    from distributed import as_completed
    from tqdm import tqdm

    t_start = time.perf_counter()
    config = config or scene.config.tracer
    det = bool(deterministic) if deterministic is not None else False
    chunk = CHAIN_CHUNK_SIZE if chunk_size is None else int(chunk_size)
    if chunk < 1:
        raise ValueError(f"chunk_size: expected >= 1, got {chunk_size}")
    if tile_size is None:
        tile_size = chunk
    if int(tile_size) < 1 or int(tile_size) % chunk:
        raise ValueError(f"tile_size {tile_size}: a tile must be a whole number of chunks "
                         f"({chunk} points), or its points share image-method calls with other "
                         "points than in one process and the paths can differ")
    plan = plan_grid(scene, tx_names, spacing, height, margin, config, method, tile_size,
                     chunk_size=chunk)
    job = TileJob(scene_folder=str(scene_folder(scene)), scene_hash=scene.content_hash(),
                  config=config, src=plan.src, src_orient=plan.src_orient, deterministic=det,
                  spec_table_size=GRID_SPEC_TABLE_SIZE,
                  keep_strongest=None if keep_strongest is None else int(keep_strongest),
                  chunk_size=chunk, worker_threads=int(worker_threads))
    pick = verify_pick(plan.todo, int(verify), config.seed)
    picked = set(pick.tolist())
    key = checkpoint_key({**job.settings(), "spacing": float(spacing), "height": plan.height,
                          "margin": float(margin), "tx_names": plan.tx_names,
                          "points": len(plan.points), "tile_size": plan.tile_size,
                          "tail_parts": plan.tail_parts})
    ckpt = TileCheckpoints(checkpoints, key) if checkpoints is not None else None
    tiles = plan.tiles
    done: dict[int, tuple[list[int], list[dict]]] = {}  # tile -> (span, parts)
    infos: dict[int, dict] = {}
    for k, tile in enumerate(tiles):
        hit = ckpt.load(k, plan.points[tile.index]) if ckpt else None
        if hit is not None:
            parts, infos[k] = hit
            done[k] = (infos[k].get("span", [0, len(tile.index)]), parts)
    resumed = len(done)
    checks: list = []  # verification futures

    def submit_checks(k: int, span: list[int], parts: list[dict]) -> None:
        idx = tiles[k].index[span[0]:span[1]]
        for j, g in enumerate(idx.tolist()):
            if g in picked:
                checks.append(client.submit(
                    verify_points, job, [g], plan.points[g:g + 1], [point_paths(parts, j)],
                    int(verify_top), pure=False, key=f"isac-verify-{key}-{g}"))

    if resumed:
        log.info("resuming: %d of %d tiles from %s", resumed, len(tiles), ckpt.dir)
    workers = len(client.scheduler_info().get("workers", {}))
    log.info("tracing %d x %d grid (%d free points) in %d tiles of %d on %d workers",
             *plan.shape, len(plan.todo), len(tiles), plan.tile_size, workers)
    t_submit = time.perf_counter()
    # each AP's chains enumerated once, by one worker; every tile takes them all
    # (Dask sends each to each worker once): shared_chains
    shots = [client.submit(shoot_source, job, s, pure=False, priority=1,
                           key=f"isac-chains-{key}-{s}")
             for s in range(len(plan.src))] if len(done) < len(tiles) else []
    futures = [client.submit(trace_tile, job, k, plan.points[tile.index], tile.part,
                             tile.parts, shots, pure=False, key=f"isac-tile-{key}-{k}")
               for k, tile in enumerate(tiles) if k not in done]
    for k in sorted(done):
        submit_checks(k, *done[k])
    runs: list[dict] = []
    try:
        with tqdm(total=len(tiles), initial=resumed, unit="tile", desc="grid tiles",
                  disable=not progress) as bar:
            for fut in as_completed(futures):
                res = fut.result()
                fut.release()
                k = res.pop("index")
                parts = res.pop("parts")
                info = {"chains": res["chains"], "span": res.pop("span")}
                if ckpt:
                    ckpt.save(k, plan.points[tiles[k].index], parts, info)
                done[k], infos[k] = (info["span"], parts), info
                submit_checks(k, info["span"], parts)
                runs.append(res)
                bar.update(1)
                if on_tile is not None:
                    on_tile({"index": k, **res})
        shot = [{k: v for k, v in f.result().items() if k != "chains"} for f in shots]
        client.cancel(shots)  # (released: the workers may drop the chains)
        t_traced = time.perf_counter()
        counts, verify_s = {}, []
        for fut in as_completed(checks):
            res = fut.result()
            counts.update(zip(res["index"], res["counts"]))
            verify_s.append(round(res["verify_s"], 3))
    except BaseException:
        client.cancel(futures + shots + checks)
        raise
    t_checked = time.perf_counter()
    verification = verification_summary(pick, [counts[int(i)] for i in pick], int(verify_top),
                                        job.keep_strongest)
    pieces = []
    for k in sorted(done):
        (a, b), parts = done[k]
        pieces.append((tiles[k].index[a:b], parts))
    arrays = assemble(plan, pieces, max(1, config.max_depth))
    meta = grid_metadata(scene, plan, spacing, margin, {
        **dataclasses.asdict(config), "deterministic": det,
        # chain reuse: no candidate buffer, nothing to grow (as trace_grid records it)
        "max_num_paths_per_src_used": config.max_num_paths_per_src,
        "chunk_size": chunk, "truncation_retries": 0,
        "spec_table_size": GRID_SPEC_TABLE_SIZE, "keep_strongest": job.keep_strongest,
        "method": "chains",
        "chains": {"version": CHAIN_REUSE_VERSION, "rays_per_source": config.samples_per_src,
                   "chains": max((int(i.get("chains", 0)) for i in infos.values()),
                                 default=0)}},
        verification)
    meta["scaleout"] = {"tiles": len(tiles), "tile_size": plan.tile_size, "workers": workers,
                        "tiles_resumed": resumed, "tiles_traced": len(tiles) - resumed,
                        "checkpoint_key": key,
                        "seconds": {"plan": t_submit - t_start, "trace": t_traced - t_submit,
                                    "verify": t_checked - t_traced,
                                    "assemble": time.perf_counter() - t_checked},
                        "verify_s": verify_s,
                        "worker_runs": worker_runs(runs),
                        "chains": [{k: (round(v, 3) if isinstance(v, float) else v)
                                    for k, v in r.items() if k not in ("start", "end")}
                                   for r in shot]}
    grid = PathGrid(meta=meta, arrays=arrays)
    if out is not None:
        save_grid(grid, out)
    if ckpt:
        ckpt.remove()
    return grid


def worker_runs(runs: list[dict]) -> list[dict]:
    """Per worker process, from the tiles it traced (``trace_tile``'s summaries):
    ``pid``, ``tiles``, ``setup_s`` (scene load, tracer), ``trace_s`` (tracing;
    its first tile includes taking the shipped chains), ``cpu_s`` (the worker
    process's CPU time in its tiles), ``first_trace_s``,
    ``idle_end_s`` (from its last tile's end to the last tile's end of any
    worker: the imbalance at the end), all in seconds."""
    if not runs:
        return []
    end = max(r["end"] for r in runs)
    out = []
    for pid in sorted({r["pid"] for r in runs}):
        mine = sorted((r for r in runs if r["pid"] == pid), key=lambda r: r["start"])
        out.append({"pid": int(pid), "tiles": len(mine),
                    "setup_s": round(sum(r["setup_s"] for r in mine), 3),
                    "trace_s": round(sum(r["trace_s"] for r in mine), 3),
                    "cpu_s": round(sum(r["cpu_s"] for r in mine), 3),
                    "first_trace_s": round(mine[0]["trace_s"], 3),
                    "idle_end_s": round(end - mine[-1]["end"], 3)})
    return out


def assemble(plan: GridPlan, tiles: list[tuple[np.ndarray, list[dict]]],
             depth: int) -> dict[str, np.ndarray]:
    """The grid arrays (:data:`~isac_twin.raytrace.grid.GRID_ARRAYS`) from traced tiles.

    Args:
        plan: the raster.
        tiles: ``(point indices [T], parts)``; a part is a ``sorted_chunk`` dict
            ``[t, S, P']``, the parts of a tile cover its points in order.
        depth: interaction slots ``D``.
    """
    pieces = []
    for idx, parts in tiles:
        off = 0
        for part in parts:
            n = part["num_paths"].shape[0]
            pieces.append((idx[off:off + n], part))
            off += n
        if off != len(idx):
            raise ValueError(f"a tile returned {off} points, expected {len(idx)}")
    return assemble_grid(plan, pieces, depth)
