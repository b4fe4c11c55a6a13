"""Live link benchmark: Blender-side cost per update, engine-to-Blender latency, memory.

Run with the project's interpreter (needs ``bpy``)::

    .venv/bin/python bench/bench_live.py            # 10,000 updates at 60/s (~3 min)
    .venv/bin/python bench/bench_live.py --quick    # 1,000 updates

1. Cost per update (1 robot, 500 ray polylines): decode the frames and apply
   ``state`` + ``rays`` (packed) + ``metrics`` with the add-on's live view (one
   hair-curves object rebuilt), against a baseline measured in the same run:
   the naive view that rebuilds one curve object per ray.
1b. The full view per state (``--view-only`` runs just this): the lab's ``scene`` message
   (labelled APs and robot), a 5 cm radio map shown, 500 rays, trails at their full 500
   points, the metrics text: decode, each ``apply_*`` and the depsgraph update (what
   Blender evaluates before it draws) per state, median and minimum, with the rays packed
   (``rays``, wire 1.3) against the same states as JSON ``paths`` (wire 1.2) in the same
   run (interleaved halves), and their ratio.
2. Latency: ``isac-twin serve`` (real Sionna tracing, box room) in a
   subprocess; time from the engine publishing a step (``state.sent_at``) to
   the add-on having applied it, over loopback.
3. Memory: a loopback sender streams updates at 60/s to the add-on's
   :class:`~addon.live.LiveClient` + live view; RSS, object and datablock counts before
   and after (Python heap too with ``--tracemalloc``). Prints figures; asserts nothing.
"""

from __future__ import annotations

import argparse
import collections
import math
import os
import random
import socket
import statistics
import sys
import tempfile
import threading
import time
import tracemalloc
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import bpy  # noqa: E402

import addon  # noqa: E402
from addon import live, live_view, wire  # noqa: E402


def rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def messages(step: int, n_rays: int = 500, seed: int = 0) -> list[dict]:
    """state + paths (n_rays polylines, 0-3 interactions, in an 8 x 6 x 3 m room) + metrics."""
    rng = random.Random(seed + step)
    tx, rx = [0.05, 3.0, 2.0], [4 + math.cos(step / 50), 3 + math.sin(step / 50), 0.25]
    paths = []
    for i in range(n_rays):
        k = rng.randint(0, 3)
        pts = [tx] + [[round(rng.uniform(0, 8), 4), round(rng.uniform(0, 6), 4),
                       round(rng.uniform(0, 3), 4)] for _ in range(k)] + [rx]
        paths.append({"points": pts, "types": [rng.choice((1, 1, 4, 8)) for _ in range(k)],
                      "power_db": -50.0 - 0.1 * i, "tau_s": 1e-8 + 1e-10 * i})
    return [
        {"type": "state", "step": step, "time_s": 0.1 * step, "sent_at": time.time(),
         "robots": [{"name": "robot1", "pose": [rx[0], rx[1], 0, 0, 0, step / 50],
                     "velocity": [0.2, 0.0], "odometry": [rx[0], rx[1], step / 50],
                     "estimate": [rx[0] + 0.05, rx[1] - 0.03, 0.0]}]},
        {"type": "paths", "step": step,
         "links": [{"tx": "AP1", "rx": "robot1", "num_paths": n_rays, "paths": paths}]},
        # the SNR changes every step, as it does for a moving robot (the text is re-laid out)
        {"type": "metrics", "step": step, "links": [{
            "tx": "AP1", "rx": "robot1", "snr_db": 30.0 + 0.1 * (step % 50),
            "rate_bps": 1e8 + 1e6 * (step % 50), "num_paths": n_rays}]},
    ]


def packed(msg: dict) -> dict:
    """The ``rays`` message (wire 1.3, what the engine sends a 1.3 viewer) of a ``paths``
    message: the same polylines as float32 little-endian arrays."""
    import numpy as np

    links = []
    for lk in msg["links"]:
        ps = lk["paths"]
        links.append(wire.rays_link(
            lk["tx"], lk["rx"], lk["num_paths"],
            sizes=np.array([len(p["points"]) for p in ps], np.uint8).tobytes(),
            points=np.array([q for p in ps for q in p["points"]], "<f4").tobytes(),
            types=np.array([t for p in ps for t in p["types"]], np.uint8).tobytes(),
            power_db=np.array([p["power_db"] for p in ps], "<f4").tobytes(),
            tau_s=np.array([p["tau_s"] for p in ps], "<f4").tobytes()))
    return {"type": "rays", "step": msg["step"], "links": links}


def packed_messages(step: int, n_rays: int = 500, seed: int = 0) -> list[dict]:
    """:func:`messages` with the rays packed (``rays`` instead of ``paths``)."""
    ms = messages(step, n_rays, seed)
    return [packed(m) if m["type"] == "paths" else m for m in ms]


def naive_rays(scene, msg: dict) -> None:
    """Baseline: delete and recreate one poly-curve object per ray."""
    coll = bpy.data.collections.get("naive") or bpy.data.collections.new("naive")
    if coll.name not in scene.collection.children:
        scene.collection.children.link(coll)
    for obj in list(coll.objects):
        data = obj.data
        bpy.data.objects.remove(obj)
        bpy.data.curves.remove(data)
    for lk in msg["links"]:
        for i, p in enumerate(lk["paths"]):
            cu = bpy.data.curves.new(f"ray{i}", "CURVE")
            cu.dimensions = "3D"
            sp = cu.splines.new("POLY")
            sp.points.add(len(p["points"]) - 1)
            sp.points.foreach_set("co", [c for q in p["points"] for c in (*q, 1.0)])
            coll.objects.link(bpy.data.objects.new(f"ray{i}", cu))


def bench_update_cost(scene, reps: int) -> None:
    frames = [b"".join(wire.encode(m) for m in packed_messages(k)) for k in range(reps)]
    view = live_view.LiveView()
    dec = wire.Decoder("e2v")
    for m in dec.feed(frames[0]):  # warm-up (creates the objects)
        live_view.apply_message(scene, m, view)
    ts = []
    for f in frames[1:]:
        t0 = time.perf_counter()
        for m in dec.feed(f):
            live_view.apply_message(scene, m, view)
        ts.append(time.perf_counter() - t0)
    ours = statistics.median(ts)
    paths = messages(0)[1]
    tb = []
    for _ in range(max(3, reps // 20)):
        t0 = time.perf_counter()
        naive_rays(scene, paths)
        tb.append(time.perf_counter() - t0)
    base = statistics.median(tb)
    coll = bpy.data.collections["naive"]
    for obj in list(coll.objects):
        data = obj.data
        bpy.data.objects.remove(obj)
        bpy.data.curves.remove(data)
    bpy.data.collections.remove(coll)
    print(f"[cost] 1 robot + 500 ray polylines, decode + apply state/rays/metrics: "
          f"median {ours * 1e3:.2f} ms, p95 {sorted(ts)[int(0.95 * len(ts))] * 1e3:.2f} ms "
          f"over {len(ts)} updates (frame {len(frames[1]) / 1024:.0f} KiB)")
    print(f"[cost] baseline, one curve object per ray (rays only): median {base * 1e3:.1f} ms "
          f"-> ratio {base / ours:.0f}x")


def lab_scene_message() -> dict:
    """A ``scene`` message like the bundled lab's: 2 access points, 1 robot, 8 x 6 x 3 m."""
    return {"type": "scene", "name": "lab", "content_hash": "0" * 64, "frequency_hz": 2.4e9,
            "objects": [{"name": "floor", "material": "concrete", "thickness": 0.2,
                         "bounds_min": [0.0, 0.0, -0.2], "bounds_max": [8.0, 6.0, 0.0]},
                        {"name": "walls", "material": "concrete", "thickness": 0.2,
                         "bounds_min": [-0.2, -0.2, 0.0], "bounds_max": [8.2, 6.2, 3.0]}],
            "devices": [{"name": "AP1", "kind": "access_point", "role": "tx",
                         "position": [0.05, 3.0, 2.0], "array": [4, 8]},
                        {"name": "AP2", "kind": "access_point", "role": "tx",
                         "position": [4.0, 0.05, 2.0], "array": [1, 1]},
                        {"name": "robot1", "kind": "robot", "role": "rx",
                         "position": [5.5, 3.0, 0.0], "model": "burger", "array": [1, 2]}],
            "links": [["AP1", "robot1"], ["AP2", "robot1"]]}


def lab_radiomap_message(cell: float = 0.05, seed: int = 0) -> dict:
    """A ``radiomap`` message of the lab's size at ``cell`` m: AP1, AP2, best, sinr layers."""
    rng = random.Random(seed)
    nx, ny = int(round(8.4 / cell)), int(round(6.4 / cell))
    layers = []
    for name, unit in (("AP1", "dBm"), ("AP2", "dBm"), ("best", "dBm"), ("sinr", "dB")):
        vals = [None if rng.random() < 0.05 else round(rng.uniform(-90, -20), 2)
                for _ in range(nx * ny)]
        layers.append({"name": name, "unit": unit, "vmin": -90.0, "vmax": -20.0,
                       "values": vals})
    return {"type": "radiomap", "scene_hash": "0" * 64, "height": 0.25,
            "origin": [-0.2 + cell / 2, -0.2 + cell / 2], "cell_size": cell, "shape": [ny, nx],
            "layers": layers, "tx": [{"name": "AP1", "position": [0.05, 3.0, 2.0]},
                                     {"name": "AP2", "position": [4.0, 0.05, 2.0]}]}


def bench_view_cost(scene, reps: int) -> None:
    """Per state: the full view (lab scene with labels, a 5 cm radio map shown, 500 rays,
    trails of 500 points, metrics text), decode + apply and + depsgraph evaluation, with
    the rays packed (``rays``, wire 1.3) against the same states as JSON ``paths`` (1.2)."""
    from addon import radiomap_view

    live_view.clear(scene)
    view = live_view.LiveView()
    dec = wire.Decoder("e2v")
    live_view.apply_message(scene, lab_scene_message(), view)
    rmsg = lab_radiomap_message()
    t0 = time.perf_counter()
    radiomap_view.apply_radiomap(scene, rmsg, view)
    t_map = time.perf_counter() - t0
    states = [messages(k) for k in range(reps)]
    json_frames = [b"".join(wire.encode(m) for m in ms) for ms in states]
    packed_frames = [b"".join(wire.encode(packed(m) if m["type"] == "paths" else m)
                              for m in ms) for ms in states]
    for k in range(view.trail_length):  # trails at their full length from the start
        view.trails.setdefault("robot1", live_view.Trail(view.trail_length)).append(
            (4 + math.cos(k / 50), 3 + math.sin(k / 50), 0.01))
        view.estimates.setdefault("robot1", live_view.Trail(view.trail_length)).append(
            (4.05 + math.cos(k / 50), 2.97 + math.sin(k / 50), 0.0))
    for m in dec.feed(json_frames[0]):
        live_view.apply_message(scene, m, view)
    bpy.context.view_layer.update()

    def run(frames):
        per_type: dict[str, list] = collections.defaultdict(list)
        ts, te = [], []
        for f in frames:
            c0 = time.process_time()
            t0 = time.perf_counter()
            msgs = dec.feed(f)
            per_type["decode"].append(time.perf_counter() - t0)
            for m in msgs:
                t1 = time.perf_counter()
                live_view.apply_message(scene, m, view)
                per_type[m["type"]].append(time.perf_counter() - t1)
            t1 = time.perf_counter()
            ts.append(t1 - t0)
            bpy.context.view_layer.update()
            te.append(time.perf_counter() - t0)
            per_type["depsgraph"].append(time.perf_counter() - t1)
            # CPU time of the process (every thread): what the state costs whatever the
            # machine's load (wall-clock medians on shared cores include preemptions)
            per_type["cpu"].append(time.process_time() - c0)
        return ts, te, per_type

    def ms(v):
        return f"{statistics.median(v) * 1e3:.2f} (min {min(v) * 1e3:.2f})"

    # interleaved halves, so that a change of the machine's load hits both forms alike
    half = len(states) // 2
    jts, jte, jper = run(json_frames[1:half])
    pts, pte, pper = run(packed_frames[1:half])
    a, b, c = run(json_frames[half:])
    jts, jte = jts + a, jte + b
    for k, v in c.items():
        jper[k] += v
    a, b, c = run(packed_frames[half:])
    pts, pte = pts + a, pte + b
    for k, v in c.items():
        pper[k] += v
    print(f"[view] lab scene + 5 cm radio map ({rmsg['shape'][1]} x {rmsg['shape'][0]} cells, "
          f"4 layers; applied once in {t_map * 1e3:.0f} ms) + 500 rays + labels + trails of "
          f"{view.trail_length} points, per state over {len(pts)} states (frames: JSON "
          f"{len(json_frames[1]) / 1024:.0f} KiB, packed {len(packed_frames[1]) / 1024:.0f} "
          f"KiB); target <= 5 ms")
    for name, ts, te, per in (("before, JSON paths (wire 1.2)", jts, jte, jper),
                              ("after, packed rays (wire 1.3)", pts, pte, pper)):
        parts = ", ".join(f"{k} {ms(v)}" for k, v in per.items())
        print(f"[view] {name}: decode + apply {ms(ts)}, + depsgraph update {ms(te)}")
        print(f"[view]   median ms per part: {parts}")
    print(f"[view] ratio JSON / packed: decode + apply "
          f"{statistics.median(jts) / statistics.median(pts):.2f}x, with the depsgraph update "
          f"{statistics.median(jte) / statistics.median(pte):.2f}x, CPU time "
          f"{statistics.median(jper['cpu']) / statistics.median(pper['cpu']):.2f}x "
          f"(load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores)")
    live_view.clear(scene)


def bench_latency(scene, steps: int) -> None:
    from isac_twin.scene.synthetic import box_room

    tmp = Path(tempfile.mkdtemp(prefix="bench-live-"))
    folder = box_room(tmp / "box")
    eng = live.EngineProcess("", str(folder), ("--rate", "0"))
    s = live.LiveSession(scene, engine=eng)
    lat, seen = [], -1
    try:
        end = time.monotonic() + 120
        while len(lat) < steps and time.monotonic() < end:
            s.tick()
            if s.view.last_step != seen and s.view.last_latency_s is not None:
                seen = s.view.last_step
                lat.append(s.view.last_latency_s)
            time.sleep(0.0005)
    finally:
        s.close()
    if lat:
        lat = lat[2:] or lat  # first steps include Dr.Jit compilation
        print(f"[latency] engine publish -> applied in Blender over loopback (box room, real "
              f"Sionna): median {statistics.median(lat) * 1e3:.2f} ms, max "
              f"{max(lat) * 1e3:.2f} ms over {len(lat)} steps")
    else:
        print("[latency] no steps arrived:", eng.log_tail())


def _sender(port_box: list, n: int, rate: float, ready: threading.Event, stop: threading.Event):
    """A minimal engine stand-in that streams ``n`` updates at ``rate`` per second."""
    ls = socket.socket()
    ls.bind(("127.0.0.1", 0))
    ls.listen(1)
    port_box.append(ls.getsockname()[1])
    ready.set()
    ls.settimeout(30)
    c, _ = ls.accept()
    c.recv(4096)
    c.sendall(wire.encode(wire.hello("engine", "bench")))
    pre = [b"".join(wire.encode(m) for m in packed_messages(k)) for k in range(50)]
    t0 = time.perf_counter()
    for k in range(n):
        if stop.is_set():
            break
        try:
            c.sendall(pre[k % 50])
        except OSError:
            break
        delay = t0 + (k + 1) / rate - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
    time.sleep(0.5)
    c.close()
    ls.close()


def _datablocks() -> dict:
    return {k: len(getattr(bpy.data, k)) for k in ("objects", "meshes", "curves", "hair_curves",
                                                    "materials")}


def bench_memory(scene, n: int, rate: float, trace: bool) -> None:
    import gc

    box, ready, stop = [], threading.Event(), threading.Event()
    th = threading.Thread(target=_sender, args=(box, n, rate, ready, stop), daemon=True)
    th.start()
    ready.wait(10)
    client = live.LiveClient("127.0.0.1", box[0], auto_reconnect=False)
    client.connect()
    view = live_view.LiveView()
    applied, ticks, tick_s = 0, 0, 0.0
    warm, t_start = 200, time.perf_counter()
    rss0 = tm0 = objs0 = db0 = None
    while True:
        t0 = time.perf_counter()
        for m in client.tick(budget_s=0.01):
            live_view.apply_message(scene, m, view)
            applied += m["type"] == "state"
        tick_s += time.perf_counter() - t0
        ticks += 1
        if applied >= warm and rss0 is None:
            gc.collect()
            if trace:
                tracemalloc.start()
                tm0 = tracemalloc.get_traced_memory()[0]
            rss0, objs0, db0 = rss_mb(), len(gc.get_objects()), _datablocks()
        if not th.is_alive() and not client.connected:
            break
        if time.perf_counter() - t_start > n / rate + 120:
            stop.set()
            print("[memory] gave up: the stream did not finish in time")
            break
        time.sleep(1 / 240)  # a GUI timer ticks at 30-60 Hz; tick faster than updates arrive
    gc.collect()
    rss1, objs1, db1 = rss_mb(), len(gc.get_objects()), _datablocks()
    tm1 = tracemalloc.get_traced_memory()[0] if tracemalloc.is_tracing() else None
    tracemalloc.stop()
    th.join(5)
    dt = time.perf_counter() - t_start
    print(f"[memory] {n} updates (1 robot + 500 rays each) sent at {rate:g}/s in {dt:.0f} s; "
          f"{applied} applied, the rest coalesced by the client; mean tick "
          f"{tick_s / ticks * 1e3:.2f} ms over {ticks} ticks; rejections "
          f"{dict(client.decoder.rejections) or 'none'}")
    if rss0 is not None:
        print(f"[memory] after {warm} warm-up updates -> end: RSS {rss0:.1f} -> {rss1:.1f} MB "
              f"({rss1 - rss0:+.1f} MB); Python objects {objs0} -> {objs1} "
              f"({objs1 - objs0:+d}); datablocks {db0} -> {db1}")
        if tm1 is not None:
            print(f"[memory] Python heap (tracemalloc) {(tm1 - tm0) / 1024:+.0f} KiB")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="1,000 updates instead of 10,000")
    ap.add_argument("--rate", type=float, default=60.0, help="updates per second (memory test)")
    ap.add_argument("--tracemalloc", action="store_true",
                    help="also trace the Python heap during the memory test (slows it ~10x)")
    ap.add_argument("--view-only", action="store_true",
                    help="only the full view's cost per state (radio map, rays, labels, trails)")
    args = ap.parse_args(argv)
    if not hasattr(bpy.types.Scene, "isac_live"):
        addon.register()
    scene = bpy.context.scene
    if args.view_only:
        bench_view_cost(scene, 200)
        return 0
    bench_update_cost(scene, 200 if args.quick else 500)
    bench_view_cost(scene, 200 if args.quick else 500)
    bench_latency(scene, 20 if args.quick else 50)
    bench_memory(scene, 1000 if args.quick else 10000, args.rate, args.tracemalloc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
