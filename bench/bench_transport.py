"""Transport benchmark: zenoh pub->sub latency on loopback vs the in-process bus; MCAP writes.

Run: ``.venv/bin/python bench/bench_transport.py [--n 2000]``. Prints; no asserts.

* Latency: median and p99 (us) of publish -> subscriber callback for a 360-ray
  ``LaserScan`` and a ``Twist``, (a) on the in-process :class:`isac_twin.bus.bus.Bus`
  (synchronous delivery: the baseline), (b) across two zenoh sessions in one
  process over TCP loopback (CDR encode + zenoh + decode). Ratio = zenoh / bus.
* MCAP: messages/s written by :class:`isac_twin.transport.record.McapRecorder` (CDR encode +
  chunked write), LaserScan and Twist, no compression and zstd.
"""

from __future__ import annotations

import argparse
import os
import socket
import statistics
import sys
import tempfile
import threading
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from isac_twin.bus.bus import Bus  # noqa: E402
from isac_twin.bus.msgs import Header, LaserScan, Twist  # noqa: E402
from isac_twin.transport.record import McapRecorder  # noqa: E402
from isac_twin.transport.zenoh_transport import ZenohConfig, ZenohTransport  # noqa: E402


def _scan() -> LaserScan:
    return LaserScan(header=Header(stamp=time.time(), frame_id="base_scan"),
                     angle_min=-np.pi, angle_max=np.pi, angle_increment=2 * np.pi / 360,
                     range_min=0.12, range_max=12.0, ranges=np.random.rand(360) * 5,
                     intensities=np.full(360, 47.0))


def _twist() -> Twist:
    return Twist(linear=np.array([0.2, 0, 0]), angular=np.array([0, 0, 0.5]))


def _pct(xs, q):
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(q * len(xs)))]


def latency_bus(make, n: int) -> list[float]:
    bus = Bus()
    pub = bus.node("pub")
    pub.advertise("/t", type(make()))
    out, t = [], [0.0]
    bus.node("sub").subscribe("/t", type(make()), lambda m: out.append(time.perf_counter() - t[0]))
    msgs = [make() for _ in range(n)]
    for m in msgs:
        t[0] = time.perf_counter()
        pub.publish("/t", m)
    return out


def latency_zenoh(make, n: int, port: int) -> list[float]:
    a = ZenohTransport(ZenohConfig(listen=[f"tcp/127.0.0.1:{port}"]), name="pub")
    b = ZenohTransport(ZenohConfig(connect=[f"tcp/127.0.0.1:{port}"]), name="sub")
    try:
        b.wait_for_peers(1, 5)
        pub = Bus(transport=a).node("pub")
        typ = type(make())
        pub.advertise("/t", typ)
        got = threading.Event()
        out, t = [], [0.0]

        def cb(m):
            out.append(time.perf_counter() - t[0])
            got.set()

        Bus(transport=b).node("sub").subscribe("/t", typ, cb)
        time.sleep(0.5)
        msgs = [make() for _ in range(n + 50)]
        for i, m in enumerate(msgs):  # one in flight at a time: latency, not throughput
            got.clear()
            t[0] = time.perf_counter()
            pub.publish("/t", m)
            got.wait(1.0)
        return out[50:]  # warm-up dropped
    finally:
        a.close()
        b.close()


def mcap_rate(make, n: int, compression: str) -> float:
    with tempfile.TemporaryDirectory() as d:
        msgs = [make() for _ in range(n)]
        rec = McapRecorder(os.path.join(d, "b.mcap"), compression=compression)
        t0 = time.perf_counter()
        for i, m in enumerate(msgs):
            rec.write("/t", m, log_time_ns=i)
        rec.close()
        return n / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=2000, help="messages per measurement")
    args = ap.parse_args()
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    print(f"loopback latency, {args.n} messages, one in flight (us)")
    print(f"  {'message':<10} {'bus med':>8} {'bus p99':>8} {'zenoh med':>10} {'zenoh p99':>10}"
          f" {'ratio med':>10}")
    for name, make in (("LaserScan", _scan), ("Twist", _twist)):
        lb = [x * 1e6 for x in latency_bus(make, args.n)]
        lz = [x * 1e6 for x in latency_zenoh(make, args.n, port)]
        mb, mz = statistics.median(lb), statistics.median(lz)
        print(f"  {name:<10} {mb:8.1f} {_pct(lb, 0.99):8.1f} {mz:10.1f} {_pct(lz, 0.99):10.1f}"
              f" {mz / mb:9.0f}x")
    print("MCAP write (CDR encode + chunked write), messages/s")
    for name, make in (("LaserScan", _scan), ("Twist", _twist)):
        print(f"  {name:<10} none {mcap_rate(make, args.n * 5, 'none'):9.0f}   "
              f"zstd {mcap_rate(make, args.n * 5, 'zstd'):9.0f}")


if __name__ == "__main__":
    main()
