"""Per-fix cost of the joint delay-direction estimator against the delay-only MDP.

One fix = AP1's comb pilots as the case study receives them: a 4 x 8 AP, 32
ports on combs of stride 32 (32 subcarriers each, 1024 x 78.125 kHz), 2 robot
antennas, 12 paths (3-18 m, 10 dB per 5 m), 20 dB SNR, eq.-4 CSI
(:func:`isac_twin.phy.channel.cfr_at`). The baseline, in the same run, is the
delay-only :class:`~isac_twin.phy.estimation.MdpEstimator` configured as
:func:`isac_twin.localization.measurements.observe_pilots` ran it on the same
comb before the per-fix work (least squares at every order). Goal: <= 20 ms
per joint fix on the lab machine.

    .venv/bin/python bench/bench_directions.py [--fixes N]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from isac_twin.phy.arrays import PlanarArray  # noqa: E402
from isac_twin.phy.channel import cfr_at  # noqa: E402
from isac_twin.phy.directions import DelayDirectionEstimator  # noqa: E402
from isac_twin.phy.estimation import MdpEstimator  # noqa: E402
from isac_twin.phy.units import SPEED_OF_LIGHT  # noqa: E402

DF, N, STRIDE = 78125.0, 1024, 32
AP, ROBOT = PlanarArray(4, 8), PlanarArray(1, 2)


def fixes(count: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    f = (np.arange(N) - N // 2) * DF
    out = []
    for _ in range(count):
        d = np.sort(rng.uniform(3.0, 18.0, 12))
        b = np.sqrt(10 ** (-(d - d[0]) / 5)) * np.exp(2j * np.pi * rng.uniform(size=12))
        h = cfr_at(b, d / SPEED_OF_LIGHT, rng.uniform(0.5, 2.5, 12), rng.uniform(-3, 3, 12),
                   rng.uniform(1.1, 2.0, 12), rng.uniform(-1.2, 1.2, 12), f, ROBOT, AP)
        csi = np.stack([h[p::STRIDE][:N // STRIDE, :, p] for p in range(AP.num_ant)], axis=2)
        n0 = np.mean(np.abs(csi) ** 2) / 100.0
        csi = csi + np.sqrt(n0 / 2) * (rng.standard_normal(csi.shape)
                                       + 1j * rng.standard_normal(csi.shape))
        out.append(csi)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fixes", type=int, default=20)
    args = ap.parse_args()
    data = fixes(args.fixes)
    m = data[0].shape[0]
    fm = np.arange(m) * STRIDE * DF
    off = np.arange(AP.num_ant) * DF
    joint = DelayDirectionEstimator(AP, STRIDE * DF)
    # observe_pilots' delay-only configuration on the same comb, as it was before the
    # per-fix work (refinement at every order; observe_pilots now refines the chosen one)
    sub = min(m - 2, max(m // 2, 2 * 9 + 2))
    delay = MdpEstimator(STRIDE * DF, max_paths=9, subband=sub,
                         max_distance_m=SPEED_OF_LIGHT / (STRIDE * DF) * 0.9)
    joint(data[0], off)
    delay(data[0].reshape(m, -1), frequencies_hz=fm)  # warm-up
    t = time.perf_counter()
    for c in data:
        delay(c.reshape(m, -1), frequencies_hz=fm)
    t_delay = (time.perf_counter() - t) / len(data)
    t = time.perf_counter()
    comps = [len(joint(c, off)) for c in data]
    t_joint = (time.perf_counter() - t) / len(data)
    print(f"fixes: {len(data)} (AP 4x8, comb {m} x {STRIDE * DF / 1e6:g} MHz, 2 rx, 20 dB)")
    print(f"delay-only MdpEstimator:        {1e3 * t_delay:7.2f} ms/fix")
    print(f"joint delay-direction estimator: {1e3 * t_joint:7.2f} ms/fix "
          f"({np.mean(comps):.1f} components)   goal <= 20 ms")
    print(f"ratio joint / delay-only: {t_joint / t_delay:.2f}")


if __name__ == "__main__":
    main()
