"""Benchmark: one gradient step of the calibration (engine.calibration).

A 5 x 4 x 3 m synthetic room with a metal cabinet, one AP, N receiver
positions, K subcarriers; parameters: the walls' permittivity and the
cabinet's x/y offsets. Prints the mean time of a gradient step (trace with
``loop_mode="evaluated"``, CFR, backward) and, as the baseline measured in
the same run, of the same evaluation without gradients; the ratio is the
cost of Dr.Jit's AD. No assertions on time.

Run: ``python bench/bench_calibration.py [--positions 4] [--subcarriers 8]
[--rays 20000] [--repeat 3]``
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from engine import synthetic as syn  # noqa: E402
from engine.calibration import Calibrator, Measurements, Parameter, SolverSettings  # noqa: E402
from engine.scene import load_scene  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--positions", type=int, default=4)
    ap.add_argument("--subcarriers", type=int, default=8)
    ap.add_argument("--rays", type=int, default=20000)
    ap.add_argument("--depth", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        objs = syn.room_objects((5.0, 4.0, 3.0), {"Cabinet": ((3.0, 2.5, 0.0), (3.6, 3.0, 1.5),
                                                              "metal", 0.002)})
        devs = [syn.SyntheticDevice("AP1", "access_point", "tx", (0.5, 0.5, 2.0)),
                syn.SyntheticDevice("robot1", "robot", "rx", (2.0, 2.0, 0.0),
                                    extra=dict(syn.ROBOT_EXTRA))]
        folder = syn.write_scene_folder(Path(tmp) / "room", objs, devs, [("AP1", "robot1")],
                                        frequency_hz=2.4e9)
        rng = np.random.default_rng(0)
        rx = np.column_stack([rng.uniform(0.5, 2.8, a.positions), rng.uniform(0.5, 3.5,
                              a.positions), np.full(a.positions, 0.3)])
        k = np.linspace(-40e6, 40e6, a.subcarriers)
        meas = Measurements((0.5, 0.5, 2.0), rx, k, np.ones((a.positions, a.subcarriers)))
        cal = Calibrator(load_scene(folder), meas,
                         [Parameter("permittivity", "concrete"), Parameter("x", "Cabinet"),
                          Parameter("y", "Cabinet")],
                         SolverSettings(max_depth=a.depth, samples_per_src=a.rays))
        cal.evaluate(cal.initial)  # JIT warm-up
        cal.evaluate(cal.initial, grad=False)
        times = {}
        for grad in (False, True):
            t0 = time.perf_counter()
            for i in range(a.repeat):
                cal.evaluate(cal.initial + 0.001 * (i + 1) * cal.scales, grad=grad)
            times[grad] = (time.perf_counter() - t0) / a.repeat
    print(f"calibration step: {a.positions} positions x {a.subcarriers} subcarriers, "
          f"{a.rays} rays, depth {a.depth}, 3 parameters")
    print(f"  forward only (baseline): {times[False]:.3f} s")
    print(f"  gradient step:           {times[True]:.3f} s  ({times[True] / times[False]:.2f}x)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
