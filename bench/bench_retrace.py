"""Retrace speed: both APs -> the robot per twin step, in the bundled lab.

Measures the per-step time of ``SionnaTracer`` (devices moved, solver reused)
after warm-up, **interleaved in one process** (step by step, so that the load of
a shared machine hits both alike):

- ``new``: the current code path (``SolverCore`` reads Sionna's path buffer
  directly and sizes the candidate buffer from what it finds);
- ``legacy``: ``SionnaTracer(legacy=True)``, i.e. ``PathSolver.__call__`` and
  Sionna's ``Paths`` (the code path before the optimization);
- ``chains``: chain reuse (``tracer.method = "chains"``, the default; see
  ``engine/raytrace/chains.py``): the APs' chains are enumerated at the first
  step (warm-up), every step runs only Sionna's image method and field
  calculator over all of them.

and checks that ``new`` and ``legacy`` give identical paths at every step and
that chain reuse finds the 24 strongest paths per link of the direct trace. Per step it also
records Dr.Jit's kernel history: kernels launched, kernels compiled (cache
misses), kernel execution time and LLVM compile time; the rest of the wall time
is Python-side tracing of Sionna's solver and the numpy conversion.

The robot's track does not repeat earlier positions (a fresh track each run,
so Dr.Jit's on-disk kernel cache cannot hide kernels that bake per-call values).

Optionally (``--samples``) it compares smaller ``samples_per_src`` with the
configured one: time per step and how many of the 24 strongest paths per link
(and of all paths) are found. As the baseline it also builds a fresh Sionna
scene, devices and ``PathSolver`` every step. No assertions on time.

    .venv/bin/python bench/bench_retrace.py [--quick] [--steps N] [--samples 10000,30000]
"""

from __future__ import annotations

import argparse
import statistics
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
from isac_twin.raytrace import DevicePose
from isac_twin.raytrace.sionna import SionnaTracer  # noqa: E402

TOP_N = 24


def robot_track(start, steps: int, step_m: float = 0.02, seed: int | None = None):
    """Poses of a robot driving in -x at 0.5 m/s (array centre), with a random
    sub-millimetre jitter per run so that positions never repeat across runs."""
    x, y, z = start
    j = np.random.default_rng(seed).uniform(-5e-4, 5e-4, size=(steps, 2))
    return [DevicePose((x - i * step_m + j[i, 0], y + j[i, 1], z), velocity=(-0.5, 0.0, 0.0))
            for i in range(steps)]


class KernelStats:
    """Dr.Jit kernel history around one call."""

    def __init__(self):
        import drjit as dr

        self.dr = dr

    def __enter__(self):
        self.dr.set_flag(self.dr.JitFlag.KernelHistory, True)
        self.dr.kernel_history()  # clear
        self.t0 = time.perf_counter()
        return self

    def __exit__(self, *exc):
        self.wall_ms = (time.perf_counter() - self.t0) * 1e3
        h = self.dr.kernel_history()
        self.dr.set_flag(self.dr.JitFlag.KernelHistory, False)
        jit = [k for k in h if str(k["type"]).endswith("JIT")]
        self.kernels = len(h)
        self.compiled = sum(1 for k in jit if not k.get("cache_hit"))
        self.exec_ms = sum(k.get("execution_time", 0.0) for k in h)
        self.compile_ms = sum(k.get("backend_time", 0.0) for k in jit)
        self.codegen_ms = sum(k.get("codegen_time", 0.0) for k in jit)
        return False


def same_paths(a: dict, b: dict) -> bool:
    for k in a:
        la, lb = a[k], b[k]
        if la.num_paths != lb.num_paths:
            return False
        for f in ("tau", "doppler", "theta_t", "phi_t", "theta_r", "phi_r",
                  "interactions", "vertices", "pol"):
            if not np.array_equal(getattr(la, f), getattr(lb, f)):
                return False
        # ``a`` (the iso V coefficient) is formed from ``pol`` in float64 numpy
        # on both paths, in another summation order: ~1e-17 relative apart
        if not np.allclose(la.a, lb.a, rtol=1e-12, atol=0):
            return False
    return True


def top_found(ref, test, n: int | None) -> tuple[int, int]:
    """Of ``ref``'s ``n`` strongest paths, how many ``test`` has (same
    interactions, delay within 1e-6 relative)."""
    order = np.argsort(-np.abs(ref.a), kind="stable")[:n]
    found = 0
    for i in order:
        t = ref.tau[i]
        for j in np.flatnonzero(np.abs(test.tau - t) <= 1e-6 * t):
            if np.array_equal(test.interactions[j], ref.interactions[i]):
                found += 1
                break
    return found, len(order)


def summary(label: str, rows: list[KernelStats]) -> str:
    ms = [r.wall_ms for r in rows]
    med = statistics.median
    return (f"  {label:8s} median {med(ms):7.1f} ms/step (min {min(ms):.1f}, max {max(ms):.1f}); "
            f"per step: {med([r.kernels for r in rows]):.0f} kernels, "
            f"{statistics.mean([r.compiled for r in rows]):.2f} compiled "
            f"({statistics.mean([r.compile_ms for r in rows]):.1f} ms LLVM), "
            f"kernel execution {med([r.exec_ms for r in rows]):.1f} ms, "
            f"IR codegen {med([r.codegen_ms for r in rows]):.1f} ms, "
            f"other (Python tracing, transfers) "
            f"{med([r.wall_ms - r.exec_ms - r.compile_ms - r.codegen_ms for r in rows]):.1f} ms")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer steps")
    ap.add_argument("--scene", type=Path, default=bundled_scene_dir())
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--samples", default="",
                    help="comma-separated samples_per_src to compare with the config's")
    args = ap.parse_args(argv)
    steps = args.steps or (10 if args.quick else 30)
    base_steps = 3 if args.quick else 6

    scene = load_scene(args.scene)
    cfg = scene.config
    poses = device_poses(cfg)
    robot = next(d.name for d in cfg.devices if d.kind == "robot")
    track = robot_track(poses[robot].position, steps + 3)
    t = cfg.tracer
    print(f"scene {cfg.scene.name}: links {[(lk.tx, lk.rx) for lk in cfg.links]}; "
          f"deterministic={t.deterministic}, samples_per_src={t.samples_per_src}, "
          f"max_depth={t.max_depth}, max_num_paths_per_src={t.max_num_paths_per_src}")

    tracers = {"chains": SionnaTracer(replace(t, method="chains")),
               "new": SionnaTracer(replace(t, method="sbr")),
               "legacy": SionnaTracer(replace(t, method="sbr"), legacy=True)}
    for i in range(3):  # warm-up: kernel compilation
        for tr in tracers.values():
            tr(scene, {**poses, robot: track[i]})
    rows = {k: [] for k in tracers}
    identical, npaths, npaths_c = 0, [], []
    found = [0, 0]
    for i in range(steps):
        p = {**poses, robot: track[3 + i]}
        res = {}
        for k, tr in (tracers.items() if i % 2 else reversed(tracers.items())):
            with KernelStats() as ks:
                res[k] = tr(scene, p)
            rows[k].append(ks)
        identical += same_paths(res["new"], res["legacy"])
        npaths.append(sum(lp.num_paths for lp in res["new"].values()))
        npaths_c.append(sum(lp.num_paths for lp in res["chains"].values()))
        for k in res["new"]:
            f, c = top_found(res["new"][k], res["chains"][k], TOP_N)
            found[0] += f
            found[1] += c
    print(f"retrace, {steps} steps interleaved ({statistics.mean(npaths):.1f} paths per step "
          f"over {len(cfg.links)} links by direct shoot-and-bounce, "
          f"{statistics.mean(npaths_c):.1f} by chain reuse; "
          f"new == legacy at {identical}/{steps} steps: bit for bit, `a` to 1e-12):")
    for k in ("legacy", "new", "chains"):
        print(summary(k, rows[k]))
    ms = {k: [r.wall_ms for r in v] for k, v in rows.items()}
    med = {k: statistics.median(v) for k, v in ms.items()}
    mean_c = statistics.mean(ms["chains"])
    print(f"  chains: mean {mean_c:.1f} ms/step (max {max(ms['chains']):.1f} ms); "
          f"{len(tracers['chains'].chains.store)} chains of "
          f"{tracers['chains'].chains.sources_shot} sources")
    print(f"  chains vs direct: {found[0]}/{found[1]} of the {TOP_N} strongest paths per link "
          "of the direct trace found (same gain and delay)")
    print(f"ratio legacy / chains: {med['legacy'] / med['chains']:.2f}x, "
          f"direct (new) / chains: {med['new'] / med['chains']:.2f}x, "
          f"legacy / new: {med['legacy'] / med['new']:.2f}x (medians)")
    print(f"goal: retrace <= 50 ms per step; measured chains median {med['chains']:.1f} ms, "
          f"mean {mean_c:.1f} ms (direct: {med['new']:.1f} ms)")
    print(f"  new: buffer re-runs {tracers['new'].core.buffer_regrows}, "
          f"largest candidate count per source {tracers['new'].core.candidates_seen}")

    if args.samples:
        ref_tr = tracers["new"]
        t = replace(t, method="sbr")
        others = {int(s): SionnaTracer(replace(t, samples_per_src=int(s)))
                  for s in args.samples.split(",") if s}
        for tr in others.values():
            tr(scene, {**poses, robot: track[0]})
        n = min(steps, 10)
        rows_s = {s: [] for s in [t.samples_per_src, *others]}
        found = {s: [0, 0, 0, 0] for s in others}
        for i in range(n):
            p = {**poses, robot: track[3 + i]}
            with KernelStats() as ks:
                ref = ref_tr(scene, p)
            rows_s[t.samples_per_src].append(ks)
            for s, tr in others.items():
                with KernelStats() as ks:
                    res = tr(scene, p)
                rows_s[s].append(ks)
                for k in ref:
                    f, c = top_found(ref[k], res[k], TOP_N)
                    fa, ca = top_found(ref[k], res[k], None)
                    found[s][0] += f
                    found[s][1] += c
                    found[s][2] += fa
                    found[s][3] += ca
        print(f"samples_per_src (same {n} steps, interleaved; paths vs "
              f"{t.samples_per_src} samples):")
        print(summary(str(t.samples_per_src), rows_s[t.samples_per_src]))
        for s in others:
            f = found[s]
            print(summary(str(s), rows_s[s])
                  + f"\n           {TOP_N} strongest per link found {f[0]}/{f[1]}, "
                  f"all paths found {f[2]}/{f[3]}")

    def fresh(i):
        sc = load_scene(args.scene)
        SionnaTracer(replace(t, method="sbr"))(sc, {**poses, robot: track[i]})

    fresh(0)  # warm-up (kernels are cached across scenes)
    new_ms = med["new"]
    ms = []
    for i in range(base_steps):
        t0 = time.perf_counter()
        fresh(i)
        ms.append((time.perf_counter() - t0) * 1e3)
    base = statistics.median(ms)
    print(f"baseline: fresh scene + devices + solver every step: median {base:.1f} ms "
          f"({base_steps} steps); ratio baseline / new retrace {base / new_ms:.2f}x, "
          f"baseline / chains {base / med['chains']:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
