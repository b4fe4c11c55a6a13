"""Grid tracing speed: the full 5 cm floor grid of the bundled lab against both APs.

All in one process:

1. **Chunked shoot-and-bounce, old vs new, interleaved** on the first
   ``--compare-points`` free points (same chunks of the raster order): the old
   way (``SolverCore(legacy=True)``: Sionna's ``Paths``, full-size candidate
   buffer, Sionna's hash table, 16 receivers per call) and the chunked way
   (:data:`DEFAULT_CHUNK_SIZE` receivers per call, hash table of
   :data:`GRID_SPEC_TABLE_SIZE` entries) alternate per block of points, so the
   load of a shared machine hits both alike; completeness of both against
   one-receiver-per-call traces (``--verify-points``).
2. **Baseline**: a random subsample traced one point per solver call (the
   ratio the issue asks for), extrapolated to the grid.
3. **Full grid, chain reuse** (``trace_grid`` default: every chain of the
   APs enumerated once, Sionna's image method for every point), timed; its verification
   (random points re-traced directly, one per call: missing paths among all
   and among the 24 strongest per link).
4. Optional ``--full-sbr`` / ``--full-old``: the full grid by chunked
   shoot-and-bounce / the old way (slow: minutes).

No assertions on time.

    .venv/bin/python bench/bench_grid.py [--quick] [--spacing M] [--chunk-size N]
                                         [--compare-points N] [--full-sbr] [--full-old]
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import isac_twin  # noqa: E402,F401 - configures LLVM before mitsuba
from isac_twin import (
    bundled_scene_dir,  # noqa: E402
    device_poses,  # noqa: E402
    load_scene,  # noqa: E402
)
from isac_twin.raytrace.base import sionna_orientation
from isac_twin.raytrace.grid import (  # noqa: E402
    DEFAULT_CHUNK_SIZE,
    GRID_SPEC_TABLE_SIZE,
    VERIFY_TOP_N,
    grid_points,
    grid_summary,
    save_grid,
    top_missing,
    trace_grid,
)
from isac_twin.raytrace.raw import free_points  # noqa: E402
from isac_twin.raytrace.solver_core import SolverCore  # noqa: E402

OLD_CHUNK = 16


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="20 cm grid, small comparison")
    ap.add_argument("--scene", type=Path, default=bundled_scene_dir())
    ap.add_argument("--spacing", type=float, default=None)
    ap.add_argument("--margin", type=float, default=0.2,
                    help="m kept from the bounding box (the lab's walls are 0.2 m thick)")
    ap.add_argument("--chunk-size", type=int, default=None,
                    help=f"receivers per solver call, new way (default {DEFAULT_CHUNK_SIZE})")
    ap.add_argument("--compare-points", type=int, default=None,
                    help="free points traced both ways, interleaved (default 1024)")
    ap.add_argument("--verify-points", type=int, default=None,
                    help="points re-traced one per call to check completeness (default 24)")
    ap.add_argument("--full-old", action="store_true", help="also trace the full grid the old way")
    ap.add_argument("--full-sbr", action="store_true",
                    help="also trace the full grid by chunked shoot-and-bounce")
    ap.add_argument("--skip-full", action="store_true", help="only the interleaved comparison")
    ap.add_argument("--out", type=Path, default=None, help="also save the new grid NPZ")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    spacing = args.spacing or (0.2 if args.quick else 0.05)
    n_cmp = args.compare_points or (128 if args.quick else 256)
    n_ver = args.verify_points or (8 if args.quick else 24)
    chunk = args.chunk_size or DEFAULT_CHUNK_SIZE

    scene = load_scene(args.scene)
    cfg = scene.config
    cap = cfg.tracer.max_num_paths_per_src
    print(f"scene {cfg.scene.name}, tracer {cfg.tracer}")
    poses = device_poses(cfg)
    tx_names = list(dict.fromkeys(lk.tx for lk in cfg.links))
    src = np.array([poses[n].position for n in tx_names], float)
    so = np.array([sionna_orientation(poses[n].orientation) for n in tx_names])
    robots = [d for d in cfg.devices if d.kind == "robot"]
    height = poses[robots[0].name].position[2]
    origin, (nx, ny) = grid_points(scene.bounds_min, scene.bounds_max, spacing, args.margin)
    ix, iy = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    points = np.stack([origin[0] + ix.ravel() * spacing, origin[1] + iy.ravel() * spacing,
                       np.full(nx * ny, height)], axis=1)
    todo = np.flatnonzero(free_points(scene.sionna, points))
    print(f"grid {nx} x {ny} = {nx * ny} points at {spacing} m, {len(todo)} free, "
          f"{len(tx_names)} APs")

    # ------------------------------------------------------------ 1. interleaved
    old = SolverCore(cfg.tracer, deterministic=False, legacy=True)
    new = SolverCore(cfg.tracer, deterministic=False, spec_table_size=GRID_SPEC_TABLE_SIZE)
    block = int(np.lcm(OLD_CHUNK, chunk))
    n_cmp = max(block, (min(n_cmp, len(todo)) // block) * block)
    sel = todo[:n_cmp]
    for core, c in ((old, OLD_CHUNK), (new, chunk)):  # warm-up
        core.solve_endpoints(scene.sionna, src, points[todo[-c:]], cap, so)
    t_old = t_new = 0.0
    res_old, res_new = {}, {}
    for b0 in range(0, n_cmp, block):
        blk = sel[b0:b0 + block]
        for way in ((0, 1) if (b0 // block) % 2 == 0 else (1, 0)):
            core, c, res = ((old, OLD_CHUNK, res_old), (new, chunk, res_new))[way]
            t0 = time.perf_counter()
            for c0 in range(0, len(blk), c):
                raw = core.solve_endpoints(scene.sionna, src, points[blk[c0:c0 + c]], cap, so)
                assert not raw.truncated
                for r, i in enumerate(blk[c0:c0 + c]):
                    res[int(i)] = [raw.link(r, s) for s in range(len(tx_names))]
            dt = time.perf_counter() - t0
            if way == 0:
                t_old += dt
            else:
                t_new += dt
    po, pn = t_old / n_cmp, t_new / n_cmp
    print(f"1. interleaved on {n_cmp} free points:")
    print(f"   old ({OLD_CHUNK}/call, Sionna's hash table, Paths): {po * 1e3:.2f} ms/point "
          f"-> {po * len(todo):.0f} s extrapolated to the grid")
    print(f"   new ({chunk}/call, table {GRID_SPEC_TABLE_SIZE} per source): {pn * 1e3:.2f} "
          f"ms/point -> {pn * len(todo):.0f} s extrapolated; ratio old/new {po / pn:.2f}x")

    # completeness vs one-receiver-per-call traces
    rng = np.random.default_rng(0)
    ver = rng.choice(sel, size=min(n_ver, len(sel)), replace=False)
    tally = {"old": [0, 0, 0, 0], "new": [0, 0, 0, 0]}
    for i in ver:
        raw = new.solve_endpoints(scene.sionna, src, points[i:i + 1], cap, so)
        for s in range(len(tx_names)):
            ref = raw.link(0, s)
            for way, res in (("old", res_old), ("new", res_new)):
                m, c = top_missing(ref, res[int(i)][s], VERIFY_TOP_N)
                ma, ca = top_missing(ref, res[int(i)][s], 10 ** 9)
                t = tally[way]
                t[0] += m
                t[1] += c
                t[2] += ma
                t[3] += ca
    for way, t in tally.items():
        print(f"   {way}: vs one receiver per call at {len(ver)} points: "
              f"{t[0]} of {t[1]} of the {VERIFY_TOP_N} strongest paths per link missing, "
              f"{t[2]} of {t[3]} of all paths missing")

    if args.skip_full:
        return 0
    # ------------------------------------------------------------ 2. full grid
    # Baseline named by the issue: a subsample traced one point per solver call.
    base_pts = rng.choice(todo, size=min(n_ver, len(todo)), replace=False)
    new.solve_endpoints(scene.sionna, src, points[base_pts[:1]], cap, so)  # warm-up
    t0 = time.perf_counter()
    for i in base_pts:
        new.solve_endpoints(scene.sionna, src, points[i:i + 1], cap, so)
    p1 = (time.perf_counter() - t0) / len(base_pts)
    print(f"2. baseline, one point per solver call ({len(base_pts)} points): {p1 * 1e3:.1f} "
          f"ms/point -> {p1 * len(todo):.0f} s extrapolated to the grid")
    t0 = time.perf_counter()
    g = trace_grid(scene, spacing=spacing, margin=args.margin, method="chains")
    t_grid = time.perf_counter() - t0
    s = grid_summary(g)
    ch = g.meta["tracer"]["chains"]
    print(f"3. full grid, chain reuse (default): {t_grid:.1f} s "
          f"({t_grid / max(1, s['free']) * 1e3:.2f} ms per free point; {ch['chains']} chains "
          f"from {ch['rays_per_source']:.0e} rays per source), truncation retries "
          f"{s['truncation_retries']}, paths per link mean {s['mean_paths_per_link']:.1f}, "
          f"max {s['max_paths_per_link']}")
    print(f"   verification (direct traces, one point per call): {g.meta['verification']}")
    if args.out:
        save_grid(g, args.out)
    t_sbr = None
    if args.full_sbr:
        t0 = time.perf_counter()
        gs = trace_grid(scene, spacing=spacing, margin=args.margin, chunk_size=chunk,
                        method="sbr")
        t_sbr = time.perf_counter() - t0
        print(f"4. full grid, chunked shoot-and-bounce ({chunk}/call): {t_sbr:.1f} s; "
              f"ratio sbr/chains {t_sbr / t_grid:.2f}x; verification {gs.meta['verification']}")
    if args.full_old:
        t0 = time.perf_counter()
        go = trace_grid(scene, spacing=spacing, margin=args.margin, chunk_size=OLD_CHUNK,
                        spec_table_size=None, legacy=True, method="sbr")
        t_old_grid = time.perf_counter() - t0
        print(f"5. full grid, old way: {t_old_grid:.1f} s; ratio old/chains "
              f"{t_old_grid / t_grid:.2f}x; verification {go.meta['verification']}")
    print(f"ratio one-point-per-call / chains: {p1 * len(todo) / t_grid:.1f}x; "
          f"chunked sbr old/new (interleaved) {po / pn:.2f}x, chains vs chunked sbr "
          f"(extrapolated) {pn * len(todo) / t_grid:.1f}x; full grid {t_grid:.1f} s "
          f"(goal <= 30 s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
