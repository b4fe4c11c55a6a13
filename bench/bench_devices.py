"""Device I/O benchmarks against the emulators (real framing over ptys).

* OpenCR: control-table block reads (READ 10+172 through dynamixel_sdk) per
  second our driver achieves; the ROS node needs 20 Hz.
* OpenCR in the robot runtime (``--runtime``): odometry messages in 10 s while the
  emulated OAK-D streams 640 x 400 colour and depth to a zenoh viewer, against the
  same runtime without the camera (baseline, same run); and the port reads one block
  read costs with the driver's blocking read against the SDK's read timeout 0 (spin).
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


def bench_opencr_reads() -> None:
    """Port reads per block read: the driver's blocking read vs read timeout 0 (spin)."""
    with EmulatedOpenCR() as emu:
        drv = OpenCR(emu.url)
        drv.open()
        try:
            ser = drv.port.ser
            read = ser.read
            calls = {"n": 0}

            def counting(n=1):
                calls["n"] += 1
                return read(n)

            ser.read = counting
            per = {}
            for timeout in (0.0, ser.timeout):
                ser.timeout = timeout
                calls["n"] = 0
                for _ in range(50):
                    drv.read_block()
                per[timeout] = calls["n"] / 50
        finally:
            drv.close()
    (spin, t_spin), (block, t_block) = ((per[k], k) for k in sorted(per))
    print(f"OpenCR  port reads per block read: {per[t_block]:6.1f} with a {t_block * 1e3:g} ms "
          f"blocking read, {per[t_spin]:6.1f} with timeout 0 (the SDK's own: "
          f"{per[t_spin] / per[t_block]:.0f}x)")


def bench_runtime_camera(seconds: float = 10.0) -> None:
    """Odometry published by the robot runtime's OpenCR while the OAK-D streams to a
    zenoh viewer, against the runtime without the camera (same run)."""
    import socket

    from isac_twin.bus.bus import Bus
    from isac_twin.devices.runtime import RobotRuntime, robot_config_from_dict
    from isac_twin.transport.zenoh_transport import ZenohConfig, ZenohTransport

    out = {}
    for camera in (False, True):
        s = socket.socket()
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        s.close()
        cfg = robot_config_from_dict({"robot": {"emulated": True, "initial_pose": [2.0, 2.0, 0.0]},
                                      "drivers": {"oakd": camera},
                                      "network": {"listen": [f"tcp/127.0.0.1:{port}"]}})
        rt = RobotRuntime(cfg).start()
        viewer = ZenohTransport(ZenohConfig(connect=[f"tcp/127.0.0.1:{port}"]))
        try:
            viewer.wait_for_peers(1, 5.0)
            node = Bus(transport=viewer).node("viewer")
            got: dict[str, int] = {}
            for topic, typ in (("odom", "nav_msgs/msg/Odometry"),
                               ("camera/color/image_raw", "sensor_msgs/msg/Image"),
                               ("camera/depth/image_raw", "sensor_msgs/msg/Image")):
                node.subscribe(f"/robot1/{topic}", typ,
                               lambda m, k=topic: got.__setitem__(k, got.get(k, 0) + 1))
            time.sleep(3.0)  # connected, the camera's pipeline up
            st = rt.opencr.stats
            n0, t0, c0 = st.published.get("/robot1/odom", 0), st.timeouts, st.connects
            cam0 = got.get("camera/color/image_raw", 0)
            time.sleep(seconds)
            out[camera] = (st.published.get("/robot1/odom", 0) - n0, st.timeouts - t0,
                           st.connects - c0, got.get("camera/color/image_raw", 0) - cam0)
        finally:
            rt.stop()
            viewer.close()
    (base, bt, br, _), (cam, ct, cr, frames) = out[False], out[True]
    print(f"OpenCR  odometry in {seconds:g} s with the OAK-D streaming to a viewer ({frames} colour "
          f"frames received): {cam} ({ct} timeouts, {cr} reconnects); without the camera: {base} "
          f"({bt} timeouts, {br} reconnects); ratio {cam / max(base, 1):.2f}")


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
    bench_opencr_reads()
    if "--runtime" in sys.argv:
        bench_runtime_camera()
    for mode in ("standard", "express"):
        bench_rplidar(mode, 1.0)
    for mode in ("standard", "express"):
        bench_rplidar(mode, 20.0)


if __name__ == "__main__":
    main()
