"""Scale-out speed: a floor grid traced in one process and on 1 and 2 Dask workers.

In one run, on one scene and grid (default: the bundled lab, 5 cm):

1. **Single process** (the baseline): ``trace_grid`` as ``isac-twin grid``
   traces it (chain reuse, Dr.Jit using every core), no verification re-trace.
2. **Local Dask cluster, 1 worker** and **2 workers** (spawned processes,
   one Dask thread and one Dr.Jit thread each): ``trace_grid_tiled`` (each
   AP's chains enumerated once, by one worker, and sent to every worker;
   tiles of whole chunks). The cluster
   start (seconds, printed: it includes the workers' import of Sionna RT,
   :mod:`isac_twin.scaleout.preload`) is not counted; the workers' scene loads
   and chain enumerations are.

Prints seconds, points/s, points/s per worker, the 2-vs-1 ratio (ideal 2.0),
where the time went (``meta["scaleout"]``: client and per-worker seconds) and
whether each cluster grid equals the single-process one (same path count
per point and AP, delays to 1e-6 relative). ``--building`` adds the same on
the bundled office floor (``blend_scenes/office_floor``) at
``--building-spacing``. No assertions on time.

    .venv/bin/python bench/bench_scaleout.py [--spacing M] [--tile-size N]
                                             [--chunk-size N] [--building]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import isac_twin  # noqa: E402,F401 - configures LLVM before mitsuba
from isac_twin import (
    bundled_scene_dir,  # noqa: E402
    load_scene,  # noqa: E402
)
from isac_twin.raytrace.grid import trace_grid  # noqa: E402
from isac_twin.scaleout.cluster import cluster_client, trace_grid_tiled  # noqa: E402


def _rss_mb() -> float:
    import psutil

    return psutil.Process().memory_info().rss / 2**20


def same_paths(a, b) -> bool:
    a, b = a.arrays, b.arrays
    return (a["valid"].shape == b["valid"].shape
            and np.array_equal(a["num_paths"], b["num_paths"])
            and np.array_equal(a["interactions"], b["interactions"])
            and np.allclose(a["tau"], b["tau"], rtol=1e-6, atol=0))


def breakdown(w: int, t_start: float, cpu: float, so: dict) -> str:
    """Lines per cluster run: start-up (not counted above), the client's
    planning / tracing / assembly and CPU time (the client process, with the
    local scheduler in it, shares the cores with the workers), which worker
    enumerated each AP's chains and how long it took, and per worker its scene
    load, first tile (with taking the shipped chains), mean later tile and idle
    time at the end."""
    sec = so["seconds"]
    per = []
    for r in so["worker_runs"]:
        later = (r["trace_s"] - r["first_trace_s"]) / max(1, r["tiles"] - 1)
        per.append(f"{r['tiles']} tiles, setup {r['setup_s']:.2f}, first {r['first_trace_s']:.2f}, "
                   f"later {later:.2f}/tile, idle at end {r['idle_end_s']:.2f}, "
                   f"CPU {r['cpu_s']:.2f}")
    pids = {r["pid"]: i for i, r in enumerate(so["worker_runs"])}
    shots = ", ".join(f"AP {c['source']} on worker {pids.get(c['pid'], '?')}: "
                      f"{c['count']} chains in {c['shoot_s']:.2f}"
                      + (f" (+ scene load {c['setup_s']:.2f})" if c["setup_s"] > 0.01 else "")
                      for c in so.get("chains", []))
    return (f"  {w} worker(s): cluster start {t_start:.1f} (not counted); client plan "
            f"{sec['plan']:.2f}, trace {sec['trace']:.2f}, assemble {sec['assemble']:.2f}, "
            f"client CPU {cpu:.2f}\n    chains (once per AP): {shots}\n"
            + "\n".join(f"    worker {i}: {p}" for i, p in enumerate(per)))


def run(folder: Path, spacing: float, margin: float, tile_size: int | None,
        workers: list[int], chunk_size: int) -> None:
    scene = load_scene(folder)
    t = time.perf_counter()
    ref = trace_grid(scene, spacing=spacing, margin=margin, progress=False, verify=0,
                     chunk_size=chunk_size)
    t_ref = time.perf_counter() - t
    n = int(ref.free.sum())
    print(f"\n{scene.config.scene.name}: {ref.shape[0]} x {ref.shape[1]} grid at {spacing:g} m, "
          f"{n} free points, {len(ref.tx_names)} APs; {os.cpu_count()} cores (shared), load "
          f"{os.getloadavg()[0]:.1f}", flush=True)
    print(f"{'run':<26}{'s':>8}{'points/s':>10}{'pts/s/worker':>14}{'equal':>7}"
          f"{'worker RSS MB':>15}")
    print(f"{'single process (default)':<26}{t_ref:8.1f}{n / t_ref:10.1f}{'':>14}{'ref':>7}",
          flush=True)
    rate, notes, cpu = {}, [], {}
    for w in workers:
        t = time.perf_counter()
        with cluster_client(workers=w) as client:
            client.wait_for_workers(w)
            t_start = time.perf_counter() - t
            t, t_cpu = time.perf_counter(), time.process_time()
            g = trace_grid_tiled(scene, spacing=spacing, margin=margin, client=client,
                                 tile_size=tile_size, chunk_size=chunk_size, progress=False)
            dt, t_cpu = time.perf_counter() - t, time.process_time() - t_cpu
            rss = max(client.run(_rss_mb).values())
        rate[w] = n / dt
        print(f"{f'{w} worker(s)':<26}{dt:8.1f}{rate[w]:10.1f}"
              f"{rate[w] / w:14.1f}{'yes' if same_paths(ref, g) else 'NO':>7}{rss:15.0f}",
              flush=True)
        notes.append(breakdown(w, t_start, t_cpu, g.meta["scaleout"]))
        runs = g.meta["scaleout"]["worker_runs"]
        cpu[w] = (sum(r["cpu_s"] for r in runs), max(r["cpu_s"] for r in runs))
    print("where the time went (s):")
    for line in notes:
        print(line)
    if 1 in cpu and 2 in cpu:  # what the ratio would be if each worker had its core to itself
        print(f"  workers' CPU: 1 worker {cpu[1][0]:.1f} s, 2 workers {cpu[2][0]:.1f} s in all, "
              f"{cpu[2][1]:.1f} s on the busier one: {cpu[1][0] / cpu[2][1]:.2f}x if CPU-bound "
              "(less sensitive to other load than the wall-clock ratio)", flush=True)
    if 1 in rate and 2 in rate:
        print(f"  2 workers / 1 worker = {rate[2] / rate[1]:.2f}x (target >= 1.8x); "
              f"1 worker / single process = {rate[1] / (n / t_ref):.2f}x", flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=Path, default=bundled_scene_dir())
    ap.add_argument("--spacing", type=float, default=0.05)
    ap.add_argument("--margin", type=float, default=0.0)
    ap.add_argument("--tile-size", type=int, default=None,
                    help="a multiple of --chunk-size (default: one chunk)")
    ap.add_argument("--chunk-size", type=int, default=1024,
                    help="points per ChainTracer call, in both runs (trace_grid's default 1024)")
    ap.add_argument("--building", action="store_true",
                    help="also the bundled office floor (blend_scenes/office_floor)")
    ap.add_argument("--building-spacing", type=float, default=0.5)
    args = ap.parse_args(argv)
    run(args.scene, args.spacing, args.margin, args.tile_size, [1, 2], args.chunk_size)
    if args.building:
        run(bundled_scene_dir("office_floor"), args.building_spacing, 0.0, args.tile_size,
            [1, 2], args.chunk_size)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
