"""Radio map benchmark: Sionna's RadioMapSolver floor map against the project's grid trace
of the same floor points, and against a bare Sionna call, in the same run (bundled lab,
both access points).

    .venv/bin/python bench/bench_radiomap.py                         # 5 cm cells (grid ~25 s)
    .venv/bin/python bench/bench_radiomap.py --cell 0.1 --samples 1000000

For every ray count (``--samples``, rays per access point) it prints:

* ``bare``: ``sionna.rt.RadioMapSolver`` called directly on a Sionna scene of the same
  folder with two isotropic transmitters (the floor of what any wrapper can reach);
* ``ours``: :func:`isac_twin.radiomap.radio_map.compute_radio_map` (device swap on the twin's own Sionna
  scene, free-space mask, RSS / best server / SNR / SINR, dB conversions) and its ratio
  to ``bare`` (what the project adds);
* the agreement with the grid trace (``trace_grid``, chain reuse, ``keep_strongest`` off)
  of the same points: median and P90 of |map - incoherent sum of the traced paths' powers|
  at the free cells both cover (the accuracy test's bound is a 2 dB median).

Times are the fastest of ``--reps`` warm calls with the same seed (the machine is shared:
the minimum is the least disturbed; the first call compiles Dr.Jit kernels and is printed
apart), with the CPU time of the same call (every thread; on 2 idle cores the wall time
is about half of it) and the load average. Then the grid trace's time and its ratio to
the map. Asserts nothing.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from isac_twin import load_scene  # noqa: E402
from isac_twin.radiomap.radio_map import compute_radio_map  # noqa: E402
from isac_twin.raytrace.grid import trace_grid  # noqa: E402
from isac_twin.raytrace.solver_core import load_sionna_rt  # noqa: E402


def bare_sionna(scene, rm, samples: int, reps: int) -> float:
    """Median time of ``RadioMapSolver`` alone on a fresh Sionna scene of the same folder,
    same plane, cells, transmitters and flags as ``rm`` (s)."""
    rt = load_sionna_rt()
    import mitsuba as mi

    cfg = scene.config
    sc = rt.load_scene(str(cfg.scene.file), merge_shapes=False)
    sc.frequency = cfg.scene.frequency_hz
    sc.tx_array = sc.rx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso",
                                               polarization="V")
    for n, p in zip(rm.tx_names, rm.tx_positions):
        sc.add(rt.Transmitter(n, position=mi.Point3f(*map(float, p))))
    x0, x1, y0, y1 = (float(v) for v in rm.extent())
    t = cfg.tracer
    solver = rt.RadioMapSolver()
    ts = []
    for _ in range(reps + 1):
        t0 = time.perf_counter()
        m = solver(sc, center=mi.Point3f((x0 + x1) / 2, (y0 + y1) / 2, float(rm.height)),
                   orientation=mi.Point3f(0, 0, 0), size=mi.Point2f(x1 - x0, y1 - y0),
                   cell_size=mi.Point2f(float(rm.cell_size), float(rm.cell_size)),
                   samples_per_tx=samples,
                   max_depth=t.max_depth, los=t.los, specular_reflection=t.specular_reflection,
                   diffuse_reflection=t.diffuse_reflection, refraction=t.refraction,
                   diffraction=t.diffraction, seed=t.seed)
        m.path_gain.numpy()
        ts.append(time.perf_counter() - t0)
    return min(ts[1:])


def agreement(rm, g, pw) -> np.ndarray:
    """|map - grid trace| dB at every (free grid point, AP) both cover."""
    diffs = []
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
    return np.abs(np.array(diffs))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cell", type=float, default=0.05, help="cell size / grid spacing, m")
    p.add_argument("--samples", type=int, nargs="+", default=[250_000, 500_000, 1_000_000],
                   help="rays per AP of the map (one row each)")
    p.add_argument("--reps", type=int, default=3, help="warm calls per timing")
    p.add_argument("--no-grid", action="store_true", help="timings only, no grid trace")
    args = p.parse_args(argv)
    scene = load_scene(ROOT / "blend_scenes" / "aces_lab" / "scene")
    t0 = time.perf_counter()
    compute_radio_map(scene, cell_size=args.cell, samples_per_tx=args.samples[0])
    print(f"first call (Dr.Jit compilation or its disk cache): {time.perf_counter() - t0:.2f} s")
    maps = {}
    for n in args.samples:
        ts = []
        for _ in range(args.reps):
            load = os.getloadavg()[0]
            c0, t0 = time.process_time(), time.perf_counter()
            rm = compute_radio_map(scene, cell_size=args.cell, samples_per_tx=n)
            ts.append((time.perf_counter() - t0, time.process_time() - c0, load))
        ours, cpu, load = min(ts)
        bare = bare_sionna(scene, rm, n, args.reps)
        maps[n] = (rm, ours)
        ny, nx = rm.shape
        print(f"{nx} x {ny} cells of {args.cell:g} m, {len(rm.tx_names)} APs, {n} rays/AP: "
              f"ours {ours:.3f} s (CPU {cpu:.3f} s, load average {load:.1f} on "
              f"{os.cpu_count()} cores), bare Sionna {bare:.3f} s -> ours / bare "
              f"{ours / bare:.2f}")
    if args.no_grid:
        return 0
    rm = maps[args.samples[-1]][0]
    t0 = time.perf_counter()
    g = trace_grid(scene, rm.tx_names, spacing=args.cell, height=rm.height, progress=False,
                   verify=0)
    t_grid = time.perf_counter() - t0
    pw = (np.abs(g.arrays["a"]) ** 2 * g.arrays["valid"]).sum(-1)        # [N, S]
    print(f"grid trace {g.shape[0]} x {g.shape[1]} points (chain reuse): {t_grid:.2f} s")
    for n, (rm, ours) in maps.items():
        d = agreement(rm, g, pw)
        print(f"{n} rays/AP: grid trace / map {t_grid / ours:.1f}x; map vs grid trace at "
              f"{len(d)} (point, AP) pairs: median |diff| {np.median(d):.2f} dB, "
              f"P90 {np.percentile(d, 90):.2f} dB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
