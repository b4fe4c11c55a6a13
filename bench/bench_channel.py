"""Benchmark: eq.-4 MIMO-OFDM channel synthesis (engine.phy.channel).

Paper setup: AP with 32 antennas (4 x 8) -> robot with 2 antennas (1 x 2),
N = 1024 subcarriers at 78.125 kHz, K = 14 symbols, ~60 paths.

Prints the time of ``OFDMChannel`` and of every baseline measured in the
same run, with ratios. Baselines are entries of ``BASELINES``; append more
(e.g. Sionna ``Paths.cfr``) with ``register_baseline`` -- each gets the same
path parameters and must return ``[K, N, Nr, Nt]``; results are also checked
for agreement with the vectorised synthesis. No assertions on time.

Run: ``python bench/bench_channel.py [--repeat 5]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from engine.phy.arrays import PlanarArray  # noqa: E402
from engine.phy.channel import OFDMChannel  # noqa: E402
from engine.phy.ofdm import ResourceGrid  # noqa: E402

GRID = ResourceGrid(1024, 78125.0, 14, cyclic_prefix_samples=72)
RX, TX = PlanarArray(1, 2), PlanarArray(4, 8)
NUM_PATHS = 60


def make_paths(seed: int = 0) -> dict:
    """Random but plausible indoor path parameters for one link."""
    rng = np.random.default_rng(seed)
    L = NUM_PATHS
    return dict(
        b=(rng.standard_normal(L) + 1j * rng.standard_normal(L)) * 1e-4,
        tau=np.sort(rng.uniform(10e-9, 150e-9, L)),
        doppler=rng.uniform(-20.0, 20.0, L),
        theta_r=rng.uniform(0.2, np.pi - 0.2, L), phi_r=rng.uniform(-np.pi, np.pi, L),
        theta_t=rng.uniform(0.2, np.pi - 0.2, L), phi_t=rng.uniform(-np.pi, np.pi, L),
        rx_orientation=np.array([0.5, 0.0, 0.0]), tx_orientation=np.array([1.57, 0.0, 0.0]),
    )


def naive_per_path_loop(p: dict) -> np.ndarray:
    """Baseline: straightforward Python loop over paths (numpy inside)."""
    t = GRID.symbol_times
    f = GRID.subcarrier_frequencies
    h = np.zeros((GRID.num_symbols, GRID.num_subcarriers, RX.num_ant, TX.num_ant), np.complex64)
    a_r = RX.steering_vectors(p["theta_r"], p["phi_r"], p["rx_orientation"])
    a_t = TX.steering_vectors(p["theta_t"], p["phi_t"], p["tx_orientation"])
    for l in range(len(p["b"])):
        tf = np.exp(2j * np.pi * (np.outer(t, np.full(f.size, p["doppler"][l]))
                                  - f[None, :] * p["tau"][l]))
        h += (p["b"][l] * tf[:, :, None, None] * np.outer(a_r[l], a_t[l])[None, None]).astype(np.complex64)
    return h


def naive_full_einsum(p: dict) -> np.ndarray:
    """Baseline: one-shot einsum over the full [K, N, L] kernel, complex128."""
    t = GRID.symbol_times
    f = GRID.subcarrier_frequencies
    a_r = RX.steering_vectors(p["theta_r"], p["phi_r"], p["rx_orientation"])
    a_t = TX.steering_vectors(p["theta_t"], p["phi_t"], p["tx_orientation"])
    kern = np.exp(2j * np.pi * (t[:, None, None] * p["doppler"] - f[None, :, None] * p["tau"]))
    return np.einsum("knl,l,lr,lt->knrt", kern, p["b"], a_r, a_t, optimize=True)


BASELINES: list[tuple[str, Callable[[dict], np.ndarray]]] = [
    ("naive per-path loop", naive_per_path_loop),
    ("full-kernel einsum c128", naive_full_einsum),
]


def register_baseline(name: str, fn: Callable[[dict], np.ndarray]) -> None:
    """Append a baseline (e.g. Sionna Paths.cfr) to be timed in the same run."""
    BASELINES.append((name, fn))


def best_time(fn: Callable[[], object], repeat: int) -> tuple[float, object]:
    out = fn()  # warm-up
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return min(times), out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args(argv)
    p = make_paths()
    ch = OFDMChannel(GRID, RX, TX)
    t_ours, h = best_time(lambda: ch(**p), args.repeat)
    print(f"channel synthesis {RX.num_ant}x{TX.num_ant}, N={GRID.num_subcarriers}, "
          f"K={GRID.num_symbols}, L={NUM_PATHS}: output {h.shape} {h.dtype}")
    print(f"  {'OFDMChannel (engine.phy)':28s} {t_ours * 1e3:9.2f} ms")
    scale = np.max(np.abs(h))
    for name, fn in BASELINES:
        t_b, h_b = best_time(lambda: fn(p), max(1, args.repeat // 2))
        err = np.max(np.abs(np.asarray(h_b) - h)) / scale
        print(f"  {name:28s} {t_b * 1e3:9.2f} ms   ratio {t_b / t_ours:6.1f}x   "
              f"max rel. diff {err:.1e}")


if __name__ == "__main__":
    main()
