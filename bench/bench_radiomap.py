"""Radio map benchmark: Sionna's RadioMapSolver floor map against the project's grid trace
of the same floor points, in the same run (bundled lab, both access points).

    .venv/bin/python bench/bench_radiomap.py                 # 0.1 m cells
    .venv/bin/python bench/bench_radiomap.py --cell 0.05     # the issue's 5 cm (grid: ~25 s)

Prints the map time (first call, with Dr.Jit compilation, and a warm call), the grid trace
time of the map's cell centres (``trace_grid``, chain reuse, ``keep_strongest`` off), their
ratio, and the agreement: the median |map - incoherent sum of the traced paths' powers| at
the free cells both cover. Asserts nothing.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from engine.radiomap import compute_radio_map  # noqa: E402
from engine.raytrace.grid import trace_grid  # noqa: E402
from engine.scene import load_scene  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cell", type=float, default=0.1, help="cell size / grid spacing, m")
    p.add_argument("--samples", type=int, default=1_000_000, help="rays per AP of the map")
    args = p.parse_args(argv)
    scene = load_scene(ROOT / "blend_scenes" / "aces_lab" / "scene")
    t0 = time.perf_counter()
    compute_radio_map(scene, cell_size=args.cell, samples_per_tx=args.samples)
    t_first = time.perf_counter() - t0
    t0 = time.perf_counter()
    rm = compute_radio_map(scene, cell_size=args.cell, samples_per_tx=args.samples, seed=7)
    t_map = time.perf_counter() - t0
    ny, nx = rm.shape
    print(f"radio map {nx} x {ny} cells of {args.cell:g} m, {len(rm.tx_names)} APs, "
          f"{args.samples} rays/AP: first {t_first:.2f} s, warm {t_map:.2f} s")
    # grid trace of the same floor region (its own raster on the scene box at the same spacing)
    t0 = time.perf_counter()
    g = trace_grid(scene, rm.tx_names, spacing=args.cell, height=rm.height, progress=False,
                   verify=0)
    t_grid = time.perf_counter() - t0
    print(f"grid trace {g.shape[0]} x {g.shape[1]} points (chain reuse): {t_grid:.2f} s")
    print(f"ratio grid trace / radio map (warm): {t_grid / t_map:.1f}x")
    # agreement at grid points that fall in free map cells
    diffs = []
    pw = (np.abs(g.arrays["a"]) ** 2 * g.arrays["valid"]).sum(-1)        # [N, S]
    for i in np.flatnonzero(g.arrays["free"]):
        try:
            iy, ix = rm.cell_of(g.points[i, :2])
        except ValueError:
            continue
        if not rm.free[iy, ix]:
            continue
        for s in range(len(rm.tx_names)):
            m = rm.path_gain_db[s, iy, ix]
            if np.isfinite(m) and pw[i, s] > 0:
                diffs.append(m - 10 * np.log10(pw[i, s]))
    d = np.abs(np.array(diffs))
    print(f"map vs grid trace at {len(d)} (point, AP) pairs: median |diff| {np.median(d):.2f} dB, "
          f"P90 {np.percentile(d, 90):.2f} dB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
