"""Exact paths: every backend against Sionna's own solver at a high ray count.

For ``--points`` random free floor points of the bundled lab where a robot
fits (no obstacle within ``--clearance`` m at the antenna height and near the
floor) plus points at round coordinates, each backend traces both
AP -> robot links and is compared, link by link, with a reference traced by
Sionna RT's public ``PathSolver`` (one receiver per call, ``--reference``
rays per source) and its ``Paths.cfr`` (:mod:`isac_twin.raytrace.conformance`):

- repeated paths (the chain-reuse defect of issue 12),
- reference paths missing within 40 dB of their link's strongest path
  (and the strongest missing one, dB),
- extra paths (returned by the backend, absent from the reference),
- the channel's relative error against ``Paths.cfr`` where the path sets agree,

and the time per call of each backend. ``--samples`` traces the chain-reuse
and direct backends at several ray counts (the trade-off of the default,
documented in docs/tracers.md). No assertions.

    .venv/bin/python bench/bench_paths.py [--points 20] [--reference 1e7]
                                          [--samples 1e5,1e6] [--quick]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import isac_twin  # noqa: E402,F401 - configures LLVM before mitsuba
from isac_twin import (
    bundled_scene_dir,  # noqa: E402
    device_poses,  # noqa: E402
    load_scene,  # noqa: E402
)
from isac_twin.raytrace.conformance import (  # noqa: E402
    SionnaReference,
    check_path_sets,
    compare_path_sets,
    robot_points,
)
from isac_twin.raytrace.sionna import SionnaTracer  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=Path, default=bundled_scene_dir())
    ap.add_argument("--points", type=int, default=20)
    ap.add_argument("--reference", type=float, default=1e7, help="rays per source, reference")
    ap.add_argument("--samples", default="", help="ray counts to compare, e.g. 1e5,1e6 "
                    "(default: the scene's tracer.samples_per_src)")
    ap.add_argument("--clearance", type=float, default=0.11, help="m around a robot's point")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--quick", action="store_true", help="4 points, reference 1e6")
    a = ap.parse_args(argv)
    if a.quick:
        a.points, a.reference = 4, 1e6
    scene = load_scene(a.scene)
    cfg = scene.config.tracer
    poses = device_poses(scene.config)
    robot = next(d.name for d in scene.config.devices if d.kind == "robot")
    pts = robot_points(scene, a.points, poses[robot].position[2], clearance=a.clearance,
                       seed=a.seed)
    print(f"{len(pts)} points ({a.points} random, {len(pts) - a.points} on lattice lines), "
          f"reference: Sionna PathSolver at {a.reference:.0e} rays per source")
    ref = SionnaReference(scene, int(a.reference))
    cache: dict = {}
    samples = [int(float(s)) for s in a.samples.split(",") if s] or [cfg.samples_per_src]
    t_ref = 0.0
    for sps in samples:
        for method in ("chains", "sbr"):
            tr = SionnaTracer(replace(cfg, method=method, samples_per_src=sps))
            t0 = time.perf_counter()
            res = [tr(scene, dict(poses, **{robot: replace(poses[robot], position=tuple(q))}))
                   for q in pts]
            dt = (time.perf_counter() - t0) / len(pts)
            t1 = time.perf_counter()
            comps = compare_path_sets(res, ref, cache=cache)
            t_ref += time.perf_counter() - t1
            miss = np.concatenate([c.missing_db for c in comps])
            rep = check_path_sets(comps)
            print(f"\n{method} at {sps:.0e} rays: {dt * 1e3:.0f} ms per call "
                  f"(chains: their enumeration included)")
            print("  " + str(rep).replace("\n", "\n  "))
            print(f"  strongest missing path: "
                  f"{miss.max():.1f} dB" if miss.size else "  no path missing")
    print(f"\nreference traces: {t_ref:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
