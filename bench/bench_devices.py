"""Device I/O benchmarks against the emulators (real framing over ptys).

* OpenCR: control-table block reads (READ 10+172 through dynamixel_sdk) per
  second our driver achieves; the ROS node needs 20 Hz.
* RPLIDAR: nodes/s and scans/s our driver decodes, at the device's nominal
  rates (A1 on firmware 1.29: 508 us/sample standard, 254 express, 5.5 Hz) and with the
  emulator's sample clock sped up to find the decoding ceiling.

Prints ratios against the baselines; no asserts. Run:
``.venv/bin/python bench/bench_devices.py``.
"""

from __future__ import annotations

import logging
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from isac_twin.devices.emulated_opencr import EmulatedOpenCR  # noqa: E402
from isac_twin.devices.emulated_rplidar import EmulatedRPLidar  # noqa: E402
from isac_twin.devices.opencr import OpenCR  # noqa: E402
from isac_twin.devices.rplidar import RPLidar  # noqa: E402

log = logging.getLogger("bench_devices")
ROS_READ_HZ = 20.0


def bench_opencr(seconds: float = 2.0) -> None:
    with EmulatedOpenCR() as emu:
        drv = OpenCR(emu.url)
        drv.open()
        try:
            drv.ping()
            n, t0 = 0, time.perf_counter()
            while time.perf_counter() - t0 < seconds:
                drv.read_block()
                n += 1
            dt = time.perf_counter() - t0
        finally:
            drv.close()
    rate = n / dt
    print(f"OpenCR  block reads (READ 10+172): {rate:8.1f} Hz  = {rate / ROS_READ_HZ:6.1f} x the ROS node's "
          f"{ROS_READ_HZ:.0f} Hz  ({n} reads, {drv.stats.frames_bad} bad, {drv.stats.timeouts} timeouts, "
          f"{1e3 / rate:.2f} ms/read)")


def bench_rplidar(mode: str, time_scale: float, seconds: float = 2.0) -> None:
    with EmulatedRPLidar(time_scale=time_scale) as emu:
        drv = RPLidar(emu.url, scan_mode=mode)
        drv.open()
        try:
            drv.start_scan()
            nodes = scans = 0
            t0 = time.perf_counter()
            while time.perf_counter() - t0 < seconds:
                got = drv.read_nodes(0.05)
                nodes += len(got)
                scans += len(drv.assembler.add(got, time.time()))
            dt = time.perf_counter() - t0
            drv.stop_scan()
            sent = emu.nodes_sent
        finally:
            drv.close()
    nominal_nodes = (emu.sample_rate_hz if mode == "standard" else emu.express_sample_rate_hz) * time_scale
    nominal_scans = emu.scan_rate_hz * time_scale
    print(f"RPLIDAR {mode:8s} x{time_scale:<4g}: {nodes / dt:9.0f} nodes/s ({nodes / dt / nominal_nodes:5.2f} x "
          f"nominal {nominal_nodes:.0f}), {scans / dt:6.2f} scans/s ({scans / dt / nominal_scans:5.2f} x nominal "
          f"{nominal_scans:.1f}); emulator sent {sent / dt:.0f} nodes/s, bad frames {drv.stats.frames_bad}")


def main() -> None:
    logging.basicConfig(level=logging.WARNING)
    bench_opencr()
    for mode in ("standard", "express"):
        bench_rplidar(mode, 1.0)
    for mode in ("standard", "express"):
        bench_rplidar(mode, 20.0)


if __name__ == "__main__":
    main()
