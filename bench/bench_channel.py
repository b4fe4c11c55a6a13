"""Benchmark: eq.-4 MIMO-OFDM channel synthesis (isac_twin.phy.channel).

Paper setup: AP with 32 antennas (4 x 8) -> robot with 2 antennas (1 x 2),
N = 1024 subcarriers at 78.125 kHz, K = 14 symbols, ~60 paths.

Prints the time of ``OFDMChannel`` and of every baseline measured in the
same run, with ratios. Baselines are entries of ``BASELINES``; append more
(e.g. Sionna ``Paths.cfr``) with ``register_baseline`` -- each gets the same
path parameters and must return ``[K, N, Nr, Nt]``; results are also checked
for agreement with the vectorised synthesis. No assertions on time.

Sionna baseline (issue goal: ours >= 5x faster): the bundled lab is traced with
``sionna.rt`` (AP1 4 x 8 -> robot 1 x 2, ``synthetic_array=True``, the twin's
tracer settings, ~50-60 paths), then Sionna's own ``Paths.cfr(num_time_steps=14)``
on those paths is timed against ``OFDMChannel`` on the same paths (gains at the
array centres from a 1 x 1 trace of the same scene), in the same run; the
ratio and the agreement (NMSE) are printed. Skipped if sionna.rt is missing or
with ``--no-sionna``.

Run: ``python bench/bench_channel.py [--repeat 5] [--no-sionna]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from isac_twin.phy.arrays import PlanarArray  # noqa: E402
from isac_twin.phy.channel import OFDMChannel  # noqa: E402
from isac_twin.phy.ofdm import ResourceGrid  # noqa: E402

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


def previous_engine(p: dict) -> np.ndarray:
    """Baseline: the engine's previous synthesis -- [K, N, L] kernel from two
    exponential tables, then one [K N, L] @ [L, Nr Nt] complex64 matmul."""
    t = GRID.symbol_times
    f = GRID.subcarrier_frequencies
    a_r = RX.steering_vectors(p["theta_r"], p["phi_r"], p["rx_orientation"])
    a_t = TX.steering_vectors(p["theta_t"], p["phi_t"], p["tx_orientation"])
    gains = (p["b"][:, None, None] * a_r[:, :, None] * a_t[:, None, :]).reshape(NUM_PATHS, -1)
    dp = np.exp(2j * np.pi * np.mod(np.outer(t, p["doppler"]), 1.0)).astype(np.complex64)
    de = np.exp(-2j * np.pi * np.mod(np.outer(f, p["tau"]), 1.0)).astype(np.complex64)
    kernel = dp[:, None, :] * de[None, :, :]
    out = kernel.reshape(-1, NUM_PATHS) @ gains.astype(np.complex64)
    return out.reshape(GRID.num_symbols, GRID.num_subcarriers, RX.num_ant, TX.num_ant)


BASELINES: list[tuple[str, Callable[[dict], np.ndarray]]] = [
    ("previous engine synthesis", previous_engine),
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


def sionna_baseline(repeat: int) -> None:
    """Time Sionna ``Paths.cfr`` vs ``OFDMChannel`` on the same traced lab paths."""
    try:
        import sionna.rt as rt

        import isac_twin  # noqa: F401 - configures Dr.Jit's LLVM before mitsuba
    except ImportError as exc:  # pragma: no cover
        print(f"(Sionna baseline skipped: {exc})")
        return
    from isac_twin import load_scene
    from isac_twin.phy.channel import baseband_gains

    cfg = load_scene(isac_twin.bundled_scene_dir()).config
    tc = cfg.tracer
    fc = cfg.scene.frequency_hz
    tx_pos, rx_pos = [0.05, 3.0, 2.0], [5.5, 3.0, 0.25]
    tx_o, rx_o = [0.0, 0.0, 0.0], [1.5708, 0.0, 0.0]  # [yaw, pitch, roll]

    def trace(rows_t, cols_t, rows_r, cols_r):
        scene = rt.load_scene(str(cfg.scene.file), merge_shapes=False)
        scene.frequency = fc
        scene.tx_array = rt.PlanarArray(num_rows=rows_t, num_cols=cols_t, vertical_spacing=0.5,
                                        horizontal_spacing=0.5, pattern="iso",
                                        polarization="V")
        scene.rx_array = rt.PlanarArray(num_rows=rows_r, num_cols=cols_r, vertical_spacing=0.5,
                                        horizontal_spacing=0.5, pattern="iso",
                                        polarization="V")
        scene.add(rt.Transmitter("tx", position=tx_pos, orientation=tx_o))
        scene.add(rt.Receiver("rx", position=rx_pos, orientation=rx_o, velocity=[0.0, 0.2, 0.0]))
        return rt.PathSolver()(scene, max_depth=tc.max_depth, los=tc.los,
                               specular_reflection=tc.specular_reflection,
                               diffuse_reflection=tc.diffuse_reflection,
                               refraction=tc.refraction, synthetic_array=True,
                               samples_per_src=tc.samples_per_src, seed=1)

    ref_paths = trace(4, 8, 1, 2)
    freqs = rt.subcarrier_frequencies(GRID.num_subcarriers, GRID.subcarrier_spacing_hz)

    def sionna_cfr():
        h = ref_paths.cfr(freqs, sampling_frequency=1 / GRID.symbol_duration_s,
                          num_time_steps=GRID.num_symbols, normalize_delays=False,
                          out_type="numpy")
        return h[0, :, 0, :].transpose(2, 3, 0, 1)

    p = trace(1, 1, 1, 1)
    a_re, a_im = p.a
    a = (np.asarray(a_re.numpy()) + 1j * np.asarray(a_im.numpy()))[0, 0, 0, 0]
    tau = np.asarray(p.tau.numpy())[0, 0]
    ok = tau >= 0
    ang = [np.asarray(x.numpy())[0, 0][ok] for x in (p.theta_r, p.phi_r, p.theta_t, p.phi_t)]
    dop = np.asarray(p.doppler.numpy())[0, 0][ok]
    ch = OFDMChannel(GRID, RX, TX)

    def ours():
        return ch(baseband_gains(a[ok], tau[ok], fc), tau[ok], dop, *ang,
                  rx_orientation=rx_o, tx_orientation=tx_o)

    t_s, h_s = best_time(sionna_cfr, repeat)
    t_o, h_o = best_time(ours, repeat)
    nmse = np.sum(np.abs(h_o - h_s) ** 2) / np.sum(np.abs(h_s) ** 2)
    print(f"Sionna baseline: bundled lab traced by sionna.rt, {int(ok.sum())} paths, "
          f"{RX.num_ant}x{TX.num_ant}, N={GRID.num_subcarriers}, K={GRID.num_symbols}")
    print(f"  {'OFDMChannel (isac_twin.phy)':28s} {t_o * 1e3:9.2f} ms")
    print(f"  {'sionna Paths.cfr':28s} {t_s * 1e3:9.2f} ms   ratio {t_s / t_o:6.1f}x   "
          f"NMSE {nmse:.1e}  (issue goal: >= 5x)")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--no-sionna", action="store_true", help="skip the Sionna Paths.cfr baseline")
    args = ap.parse_args(argv)
    p = make_paths()
    ch = OFDMChannel(GRID, RX, TX)
    t_ours, h = best_time(lambda: ch(**p), args.repeat)
    print(f"channel synthesis {RX.num_ant}x{TX.num_ant}, N={GRID.num_subcarriers}, "
          f"K={GRID.num_symbols}, L={NUM_PATHS}: output {h.shape} {h.dtype}")
    print(f"  {'OFDMChannel (isac_twin.phy)':28s} {t_ours * 1e3:9.2f} ms")
    scale = np.max(np.abs(h))
    for name, fn in BASELINES:
        t_b, h_b = best_time(lambda: fn(p), max(1, args.repeat // 2))
        err = np.max(np.abs(np.asarray(h_b) - h)) / scale
        print(f"  {name:28s} {t_b * 1e3:9.2f} ms   ratio {t_b / t_ours:6.1f}x   "
              f"max rel. diff {err:.1e}")
    if not args.no_sionna:
        sionna_baseline(args.repeat)


if __name__ == "__main__":
    main()
