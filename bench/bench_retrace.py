"""Retrace speed: both APs -> the robot per twin step, in the bundled lab.

Measures the per-step time of ``SionnaTracer`` (devices moved, solver reused)
after warm-up, and as the baseline, building a fresh Sionna scene, devices and
``PathSolver`` every step (measured in the same run). Prints the ratio.
No assertions on time.

    .venv/bin/python bench/bench_retrace.py [--quick] [--scene DIR] [--steps N]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import engine  # noqa: E402,F401 - configures LLVM before mitsuba
from engine.paths import bundled_scene_dir  # noqa: E402
from engine.raytrace import DevicePose, device_poses  # noqa: E402
from engine.raytrace.sionna import SionnaTracer  # noqa: E402
from engine.scene import load_scene  # noqa: E402


def robot_track(start, steps: int, step_m: float = 0.02):
    """Poses of a robot driving in -x at 0.5 m/s (array centre)."""
    x, y, z = start
    return [DevicePose((x - i * step_m, y, z), velocity=(-0.5, 0.0, 0.0)) for i in range(steps)]


def timed(fn, n: int) -> list[float]:
    out = []
    for i in range(n):
        t = time.perf_counter()
        fn(i)
        out.append((time.perf_counter() - t) * 1e3)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer steps")
    ap.add_argument("--scene", type=Path, default=bundled_scene_dir())
    ap.add_argument("--steps", type=int, default=None)
    args = ap.parse_args(argv)
    steps = args.steps or (10 if args.quick else 40)
    base_steps = 3 if args.quick else 8

    scene = load_scene(args.scene)
    cfg = scene.config
    poses = device_poses(cfg)
    robot = next(d.name for d in cfg.devices if d.kind == "robot")
    track = robot_track(poses[robot].position, steps + 3)

    print(f"scene {cfg.scene.name}: links {[(lk.tx, lk.rx) for lk in cfg.links]}")
    results = {}
    variants = [("config", cfg.tracer)]
    if not args.quick:
        variants.append(("samples_per_src=20000", replace(cfg.tracer, samples_per_src=20_000)))
    for label, tcfg in variants:
        tracer = SionnaTracer(tcfg)
        for i in range(3):  # warm-up: kernel compilation
            tracer(scene, {**poses, robot: track[i]})
        counts = []

        def step(i, tracer=tracer, counts=counts):
            res = tracer(scene, {**poses, robot: track[3 + i]})
            counts.append(sum(lp.num_paths for lp in res.values()))

        ms = timed(step, steps)
        results[label] = statistics.median(ms)
        print(f"  retrace [{label}; deterministic={tcfg.deterministic}, "
              f"samples_per_src={tcfg.samples_per_src}, max_depth={tcfg.max_depth}]: "
              f"median {statistics.median(ms):.1f} ms, min {min(ms):.1f} ms, "
              f"max {max(ms):.1f} ms per step ({steps} steps, "
              f"{statistics.mean(counts):.1f} paths per step over {len(cfg.links)} links)")

    def fresh(i):
        sc = load_scene(args.scene)
        SionnaTracer(cfg.tracer)(sc, {**poses, robot: track[i]})

    fresh(0)  # warm-up (kernels are cached across scenes)
    ms = timed(fresh, base_steps)
    base = statistics.median(ms)
    print(f"  baseline: fresh scene + devices + solver every step: median {base:.1f} ms "
          f"({base_steps} steps)")
    print(f"ratio baseline / retrace [config]: {base / results['config']:.2f}x "
          f"(goal: retrace <= 50 ms per step; measured {results['config']:.1f} ms)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
