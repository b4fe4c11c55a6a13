"""Grid tracing speed: the full 5 cm floor grid of the bundled lab against both APs.

Traces the grid (8 x 6 m interior -> 160 x 120 = 19,200 points) in chunks after
a warm-up, confirms that no chunk was truncated (``trace_grid`` splits/grows on
truncation and records the retries; the mean path count per link is compared
with one-receiver-per-call traces of a subsample), and as the baseline traces a
subsample with one solver call per point and extrapolates to the whole grid.
Prints the ratio. No assertions on time.

    .venv/bin/python bench/bench_grid.py [--quick] [--scene DIR] [--spacing M]
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import engine  # noqa: E402,F401 - configures LLVM before mitsuba
from engine.paths import bundled_scene_dir  # noqa: E402
from engine.raytrace.grid import grid_summary, save_grid, trace_grid  # noqa: E402
from engine.raytrace.sionna import SolverCore  # noqa: E402
from engine.scene import load_scene  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="20 cm grid, small subsample")
    ap.add_argument("--scene", type=Path, default=bundled_scene_dir())
    ap.add_argument("--spacing", type=float, default=None)
    ap.add_argument("--margin", type=float, default=0.2,
                    help="m kept from the bounding box (the lab's walls are 0.2 m thick)")
    ap.add_argument("--chunk-size", type=int, default=None,
                    help="receivers per solver call (default: trace_grid's)")
    ap.add_argument("--baseline-points", type=int, default=None)
    ap.add_argument("--out", type=Path, default=None, help="also save the grid NPZ")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    spacing = args.spacing or (0.2 if args.quick else 0.05)
    n_base = args.baseline_points or (20 if args.quick else 60)

    scene = load_scene(args.scene)
    cfg = scene.config
    print(f"scene {cfg.scene.name}, tracer {cfg.tracer}")
    trace_grid(scene, spacing=1.0, margin=args.margin, progress=False)  # warm-up

    t0 = time.perf_counter()
    g = trace_grid(scene, spacing=spacing, margin=args.margin, chunk_size=args.chunk_size)
    t_grid = time.perf_counter() - t0
    s = grid_summary(g)
    free = np.flatnonzero(g.free)
    print(f"grid {s['shape'][0]} x {s['shape'][1]} = {s['points']} points at {spacing} m "
          f"({s['free']} in free space) x {len(g.tx_names)} APs: {t_grid:.1f} s, "
          f"{t_grid / max(1, len(free)) * 1e3:.2f} ms per point; chunk size "
          f"{g.meta['tracer']['chunk_size']}, truncation retries {s['truncation_retries']}, "
          f"final cap {g.meta['tracer']['max_num_paths_per_src_used']}")
    print(f"  paths per link: mean {s['mean_paths_per_link']:.1f}, max {s['max_paths_per_link']}")
    if args.out:
        save_grid(g, args.out)

    # Baseline: one solver call per point on a subsample (same settings).
    rng = np.random.default_rng(0)
    sub = rng.choice(free, size=min(n_base, len(free)), replace=False)
    core = SolverCore(cfg.tracer, deterministic=False)
    src = g.tx_positions
    from engine.raytrace.base import sionna_orientation
    so = np.array([sionna_orientation(o) for o in g.tx_orientations])
    core.solve_endpoints(scene.sionna, src, g.points[sub[:1]], cfg.tracer.max_num_paths_per_src,
                         so)  # warm-up
    counts = []
    t0 = time.perf_counter()
    for i in sub:
        raw = core.solve_endpoints(scene.sionna, src, g.points[i:i + 1],
                                   cfg.tracer.max_num_paths_per_src, so)
        assert not raw.truncated
        counts.append(raw.valid.sum(-1)[0])
    t_single = (time.perf_counter() - t0) / len(sub)
    counts = np.array(counts)  # [n, S]
    grid_counts = g.num_paths[sub]
    print(f"  subsample of {len(sub)} points, one solver call each: {t_single * 1e3:.1f} ms "
          f"per point -> {t_single * len(free):.1f} s extrapolated to the grid")
    lost = np.clip(counts - grid_counts, 0, None).sum()
    print(f"  paths per link on the subsample: chunked grid {grid_counts.mean():.2f}, "
          f"single-point calls {counts.mean():.2f}: {lost} of {counts.sum()} paths "
          f"({100 * lost / max(1, counts.sum()):.2f} %) missing in the chunked grid "
          f"(Sionna's per-call candidate de-duplication, see docs/tracers.md); "
          f"trace_grid's own verification: {g.meta['verification']}")
    print(f"ratio single-point / chunked grid: {t_single * len(free) / t_grid:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
