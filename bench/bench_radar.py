"""Benchmark: OFDM radar processing of one frame (isac_twin.sensing.radar).

Frame: N = 1024 subcarriers at 78.125 kHz, K = 14 symbols (the bundled
lab's grid, all REs carry sensing symbols), 32-antenna receiver (4 x 8,
AP1), two point targets plus noise. The -6 dB second target sits in the
CA-CFAR training cells of the first (masking): CA-CFAR finds one, OS-CFAR
both. Timed per frame: symbol division,
range-Doppler map (4x range / 2x Doppler zero padding), CA-CFAR, and the
per-detection refinement (NLS range/Doppler + beamscan/Nelder-Mead angle).

Baseline in the same run: the same range-Doppler map computed naively with
a Python loop over the antennas and a 1-D FFT per subcarrier/symbol row
(what a straightforward port of a single-antenna radar would do), followed
by the same CFAR/refinement. Prints ms/frame and the ratio. No assertions.

With ``--twin STEPS`` it also measures the sensing frame cost per step in the
loop: the bundled lab's ``[[sensing]]`` radar (AP2 -> AP1, 25 % of the REs:
echo + clutter tracing with Sionna's RCS solver, eq.-4 echo channel, radar
processing, tracker) as ``Twin`` stage ``sense``, against the comms ray
tracing of the same steps (stage ``trace``, AP1/AP2 -> robot1) as the
baseline: prints ms per sensing step and the ratio.

Run: ``python bench/bench_radar.py [--repeat 5] [--twin 12]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from isac_twin.phy import OFDMChannel, PlanarArray, ResourceGrid, ResourceSet  # noqa: E402
from isac_twin.phy.units import SPEED_OF_LIGHT  # noqa: E402
from isac_twin.sensing.radar import OFDMRadar, RangeDopplerMap  # noqa: E402

GRID = ResourceGrid(1024, 78125.0, 14, cyclic_prefix_samples=72)
ARRAY = PlanarArray(4, 8)
FC = 2.4e9


def frame(seed: int = 0):
    """``y [14, 1024, 32]``, ``x [14, 1024]``: two targets (path lengths 9.6 m
    and 24 m), per-RE SNR 0 dB."""
    ch = OFDMChannel(GRID, ARRAY, PlanarArray(1, 1), dtype=np.complex128)
    d = np.array([9.6, 24.0])
    h = ch(np.array([1.0, 0.5]), d / SPEED_OF_LIGHT, np.array([0.0, 0.0]),
           np.deg2rad([100.0, 110.0]), np.deg2rad([1.0, -12.0]),
           np.deg2rad([90.0, 90.0]), np.zeros(2))[..., 0]
    rng = np.random.default_rng(seed)
    x = np.exp(1j * np.pi / 2 * rng.integers(0, 4, GRID.shape))
    z = np.sqrt(0.5) * (rng.standard_normal(h.shape) + 1j * rng.standard_normal(h.shape))
    return h * x[..., None] + z, x


def naive_range_doppler(radar: OFDMRadar, h: np.ndarray) -> RangeDopplerMap:
    """Per-antenna, per-row Python loops of 1-D FFTs (the baseline)."""
    ks, ns, nr = h.shape
    nrg, nd = ns * radar.ros, ks * radar.dos
    wk, wn = radar._win(ks), radar._win(ns)
    cube = np.zeros((nr, nd, nrg), complex)
    power = np.zeros((nd, nrg))
    for r in range(nr):
        tmp = np.zeros((ks, nrg), complex)
        for k in range(ks):
            tmp[k] = np.fft.ifft(h[k, :, r] * wn * wk[k], n=nrg) * nrg
        for m in range(nrg):
            cube[r, :, m] = np.fft.fftshift(np.fft.fft(tmp[:, m], n=nd))
        power += np.abs(cube[r]) ** 2
    d = np.arange(nrg) * (radar.max_unambiguous_path_m / nrg)
    nu = (np.arange(nd) - nd // 2) / (nd * radar.dt)
    return RangeDopplerMap(power=power, path_length_m=d, doppler_hz=nu, cube=cube)


def twin_sensing_cost(steps: int, dt: float = 0.05) -> dict:
    """Sensing frame cost in the lab twin (stage ``sense``) vs the comms trace."""
    import isac_twin
    from isac_twin import Twin

    # the frame within its own step (the default sensing worker delivers it later)
    tw = Twin.from_scene(isac_twin.bundled_scene_dir(), dt=dt, phy=False, sync_sensing=True)
    every = tw.radar.links[0].every
    for _ in tw.run(2 * every):  # warm-up: Sionna scenes, kernels, background
        pass
    sense, trace, frames = [], [], 0
    for r in tw.run(steps):
        trace.append(r.timings_s["trace"])
        if r.sensing is not None:
            sense.append(r.timings_s["sense"])
            frames += 1
    s_ms, t_ms = 1e3 * float(np.mean(sense)), 1e3 * float(np.mean(trace))
    print(f"twin loop ({steps} steps, dt {dt} s, radar every {every}): sensing frame "
          f"{s_ms:.1f} ms (min {1e3 * min(sense):.1f}, {frames} frames), comms trace "
          f"{t_ms:.1f} ms/step -> sensing frame / comms trace x{s_ms / t_ms:.2f}; "
          f"{s_ms / every:.1f} ms per step on average")
    return dict(sense_ms=s_ms, trace_ms=t_ms, every=every)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--twin", type=int, default=0, metavar="STEPS",
                    help="also measure the sensing frame cost in the lab twin")
    a = ap.parse_args()
    if a.twin > 0:
        twin_sensing_cost(a.twin)
    radar = OFDMRadar(ResourceSet(GRID, name="AP2->AP1"), FC, rx_array=ARRAY,
                      max_detections=4)
    y, x = frame()
    radar(y, x)  # warm-up (beamscan grid, FFT plans)

    def ours():
        return radar(y, x)

    def naive():
        h = radar.channel_estimate(y, x)
        return radar.process(h, rd=naive_range_doppler(radar, h))

    radar_os = OFDMRadar(ResourceSet(GRID, name="AP2->AP1"), FC, rx_array=ARRAY,
                         max_detections=4, cfar="os")
    radar_os(y, x)

    def ours_os():
        return radar_os(y, x)

    times = {}
    for name, fn in (("vectorised (CA-CFAR)", ours), ("vectorised (OS-CFAR)", ours_os),
                     ("naive per-antenna loop", naive)):
        best = np.inf
        for _ in range(a.repeat):
            t0 = time.perf_counter()
            dets, rd = fn()
            best = min(best, time.perf_counter() - t0)
        times[name] = best
        print(f"{name:24s} {1e3 * best:8.1f} ms/frame  ({len(dets)} detections: "
              + ", ".join(f"{d.path_length_m:.2f} m/{np.rad2deg(d.azimuth_rad):.1f} deg"
                          for d in dets) + ")")
    h = radar.channel_estimate(y, x)
    t_rd = t_rdn = np.inf
    for _ in range(a.repeat):
        t0 = time.perf_counter()
        rd = radar.range_doppler(h)
        t_rd = min(t_rd, time.perf_counter() - t0)
        t0 = time.perf_counter()
        rd_n = naive_range_doppler(radar, h)
        t_rdn = min(t_rdn, time.perf_counter() - t0)
    assert np.allclose(rd.power, rd_n.power, rtol=1e-6, atol=1e-9 * rd.power.max())
    print(f"range-Doppler map only: vectorised {1e3 * t_rd:.1f} ms, naive {1e3 * t_rdn:.1f} ms "
          f"(x{t_rdn / t_rd:.1f})")
    ratio = times["naive per-antenna loop"] / times["vectorised (CA-CFAR)"]
    print(f"full frame speed-up vs naive: x{ratio:.1f} "
          f"(frame 14 x 1024 x 32, map {rd.power.shape[0]} x {rd.power.shape[1]})")


if __name__ == "__main__":
    main()
